"""Evaluation harness: the paper's protocol (docs/EVALUATION.md) on KITTI-layout sequences.

- :mod:`.metrics`: Recall@N, MRR, RTE/RRE, pose success;
- :mod:`.splits`: database/query splits by time or loop-closure gap;
- :mod:`.cache`: on-disk feature cache keyed by encoder identity and scan file;
- :mod:`.runner`: every re-ranking method x top-k, plus the n_topk sweep;
- :mod:`.report`: Markdown table, JSON and the n_topk plot.

Heavy dependencies (torch, Open3D, matplotlib) are imported by the modules that need them.
"""
