"""Spare cores (sgvloc.core.cores): the thread share, and the stages that take it give
the same answers at any thread count."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from sgvloc.core import cores
from sgvloc.core.encoders import LearnedEncoder
from sgvloc.core.pose import IcpTarget, _fit_quality
from sgvloc.core.sequence import KittiSequence


@pytest.fixture
def four_cores() -> Iterator[None]:
    cores.set_cores(4)
    try:
        yield
    finally:
        cores.set_cores(1)


def test_threads_divide_the_cores_among_busy_workers(four_cores: None) -> None:
    assert cores.threads() == 4  # nothing busy: a stage called outside a worker
    inside: list[int] = []
    entered, recorded, release = threading.Barrier(3), threading.Barrier(3), threading.Event()

    def worker() -> None:
        with cores.busy():
            with cores.busy():  # nested: counted once
                entered.wait()
                inside.append(cores.threads())
                recorded.wait()
                release.wait()

    others = [threading.Thread(target=worker) for _ in range(2)]
    for t in others:
        t.start()
    entered.wait()
    recorded.wait()
    assert inside == [2, 2]  # 4 cores, 2 busy workers
    with cores.busy():
        assert cores.threads() == 1  # 4 // 3
    release.set()
    for t in others:
        t.join()
    assert cores.threads() == 4


def test_one_core_means_one_thread_and_bad_counts_are_refused() -> None:
    assert cores.cores() == 1 and cores.threads() == 1  # outside the service
    with pytest.raises(ValueError, match="cores must be >= 1"):
        cores.set_cores(0)


def test_network_forward_is_the_same_on_spare_cores(balm_mini_dir: Path, four_cores: None) -> None:
    enc = LearnedEncoder(runtime="onnx")  # made after set_cores: it holds both sessions
    scan = KittiSequence(balm_mini_dir)[0].scan().points
    with cores.busy(), cores.busy():  # one busy worker: the call takes 4 threads
        assert cores.threads() == 4
        wide = enc.encode(scan)
    with cores.busy():
        cores.set_cores(1)
        narrow = enc.encode(scan)
    np.testing.assert_array_equal(wide.global_descriptor, narrow.global_descriptor)
    np.testing.assert_array_equal(wide.keypoints, narrow.keypoints)
    np.testing.assert_array_equal(wide.local_features, narrow.local_features)
    assert 4 in enc.net._sessions and len(enc.net._sessions) == 2  # the narrow one, 4


def test_icp_and_fitness_are_the_same_on_spare_cores(four_cores: None) -> None:
    rng = np.random.default_rng(3)
    cloud = rng.uniform(-20, 20, size=(6000, 3))
    cloud[:3000, 2] = rng.normal(0, 0.02, 3000)  # a ground plane among scattered points
    pts = cloud[rng.choice(len(cloud), 3000)] + rng.normal(scale=0.3, size=(3000, 3))
    T = np.eye(4)
    T[:3, 3] = [0.2, -0.1, 0.05]
    small, numba = IcpTarget(cloud), IcpTarget(cloud, "numba")
    assert numba.numba is not None

    def run() -> tuple:
        aligned, iterations = numba.numba.align(pts, T, 1.0, 10, 1e-4, 1e-4)
        return (
            _fit_quality(small.tree, pts, T, 1.0, small.cloud.normals()),
            numba.numba.fit_quality(pts, T, 1.0),
            aligned,
            iterations,
        )

    assert cores.threads() == 4
    wide = run()
    cores.set_cores(1)
    narrow = run()
    assert wide[0][:2] == narrow[0][:2]  # small_gicp's search on 4 threads and on 1
    np.testing.assert_array_equal(wide[0][2], narrow[0][2])
    assert wide[1][:2] == narrow[1][:2] and wide[3] == narrow[3]
    np.testing.assert_array_equal(wide[1][2], narrow[1][2])  # the normals' moment
    np.testing.assert_array_equal(wide[2], narrow[2])
