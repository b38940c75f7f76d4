"""Scan readers/writers and KITTI sequences: generated files plus the balm_mini fixture."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from sgvloc.core.errors import InputError, ScanFormatError
from sgvloc.core.io import (
    Scan,
    read_kitti_bin,
    read_npy,
    read_pcd,
    read_ply,
    read_scan,
    scan_from_array,
    write_kitti_bin,
    write_pcd,
    write_ply,
)
from sgvloc.core.sequence import KittiSequence, read_poses, relative_pose


def _xyzi(rng: np.random.Generator, n: int = 50) -> np.ndarray:
    a = rng.normal(scale=10.0, size=(n, 4)).astype(np.float32)  # [n, 4]
    a[:, 3] = rng.integers(0, 255, size=n)
    return a


def _raises_naming(path: Path, *match: str):
    """Context manager: ScanFormatError whose message names ``path`` and each ``match``."""

    class _Ctx:
        def __enter__(self):
            self.cm = pytest.raises(ScanFormatError)
            self.info = self.cm.__enter__()
            return self.info

        def __exit__(self, *exc):
            handled = self.cm.__exit__(*exc)
            msg = str(self.info.value)
            assert path.name in msg, msg
            for m in match:
                assert m in msg, msg
            return handled

    return _Ctx()


# ------------------------------------------------------------------------------- .bin


def test_kitti_bin_read(tmp_path, rng):
    a = _xyzi(rng)
    p = tmp_path / "000000.bin"
    a.tofile(p)
    s = read_kitti_bin(p)
    assert s.points.dtype == np.float32 and s.points.shape == (50, 3)
    np.testing.assert_array_equal(s.points, a[:, :3])
    np.testing.assert_array_equal(s.intensity, a[:, 3])
    assert s.source == str(p)


def test_kitti_bin_bad_size(tmp_path):
    p = tmp_path / "short.bin"
    p.write_bytes(b"\x00" * 10)
    with _raises_naming(p, "10 bytes", "multiple of 16"):
        read_scan(p)


# ------------------------------------------------------------------------------- PCD


def test_pcd_ascii(tmp_path):
    p = tmp_path / "a.pcd"
    p.write_text(
        "# .PCD v.7 - Point Cloud Data file format\n"
        "VERSION .7\nFIELDS intensity x y z\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        "WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n"
        "7 1 2 3\n8 4.5 -5 6e1\n\n9 nan 0 0\n"
    )
    s = read_pcd(p)
    np.testing.assert_array_equal(s.points[:2], [[1, 2, 3], [4.5, -5, 60]])
    assert np.isnan(s.points[2, 0])  # non-finite rows are kept for preprocessing
    np.testing.assert_array_equal(s.intensity, [7, 8, 9])


def test_pcd_binary_odd_fields(tmp_path, rng):
    """Extra fields in odd order: float64 t, uint16 ring, COUNT-3 padding, int8, x y z last."""
    n = 40
    dt = np.dtype(
        [
            ("t", "<f8"),
            ("ring", "<u2"),
            ("z", "<f4"),
            ("pad", "<u1", (3,)),
            ("intensity", "<f4"),
            ("x", "<f4"),
            ("tag", "<i1"),
            ("y", "<f4"),
        ]
    )
    assert dt.itemsize == 8 + 2 + 4 + 3 + 4 + 4 + 1 + 4  # packed, as PCD requires
    rec = np.zeros(n, dtype=dt)
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["t"] = np.linspace(0, 0.1, n)
    rec["ring"] = np.arange(n) % 128 + 60000  # above int16 range: must be read as uint16
    rec["intensity"] = np.arange(n)
    rec["tag"] = -1
    header = (
        "VERSION 0.7\nFIELDS t ring z _ intensity x tag y\nSIZE 8 2 4 1 4 4 1 4\n"
        "TYPE F U F U F F I F\nCOUNT 1 1 1 3 1 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n"
    )
    p = tmp_path / "odd.pcd"
    p.write_bytes(header.encode() + rec.tobytes())
    s = read_scan(p)
    np.testing.assert_array_equal(s.points, xyz)
    np.testing.assert_array_equal(s.intensity, np.arange(n, dtype=np.float32))


def _pcd_compressed(path: Path, cols: dict[str, np.ndarray], literal_only: bool = True) -> None:
    """Write a binary_compressed PCD (float32 fields) using an all-literal LZF stream."""
    n = len(next(iter(cols.values())))
    raw = b"".join(np.asarray(c, dtype="<f4").tobytes() for c in cols.values())
    lzf = b"".join(
        bytes([len(raw[i : i + 32]) - 1]) + raw[i : i + 32] for i in range(0, len(raw), 32)
    )
    nf = len(cols)
    header = (
        f"VERSION 0.7\nFIELDS {' '.join(cols)}\nSIZE {' '.join(['4'] * nf)}\n"
        f"TYPE {' '.join(['F'] * nf)}\nCOUNT {' '.join(['1'] * nf)}\nWIDTH {n}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary_compressed\n"
    )
    path.write_bytes(header.encode() + struct.pack("<II", len(lzf), len(raw)) + lzf)


def test_pcd_binary_compressed_literal(tmp_path, rng):
    a = _xyzi(rng, 30)
    p = tmp_path / "c.pcd"
    _pcd_compressed(p, {"y": a[:, 1], "intensity": a[:, 3], "x": a[:, 0], "z": a[:, 2]})
    s = read_pcd(p)
    np.testing.assert_array_equal(s.points, a[:, :3])
    np.testing.assert_array_equal(s.intensity, a[:, 3])


def _pcd_lzf(path: Path, n: int, stream: bytes) -> None:
    """A binary_compressed PCD of ``n`` float32 points x y z whose LZF data is ``stream``."""
    header = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary_compressed\n"
    )
    path.write_bytes(header.encode() + struct.pack("<II", len(stream), n * 12) + stream)


def test_pcd_lzf_back_references(tmp_path):
    # literal: one float 1.0; then a long back reference (length 7 + 35 + 2 = 44 bytes at
    # distance 3 + 1) that reads the bytes it writes: all 4 points x 3 fields are 1.0
    stream = bytes([3]) + struct.pack("<f", 1.0) + bytes([7 << 5, 35, 3])
    p = tmp_path / "ref.pcd"
    _pcd_lzf(p, 4, stream)
    np.testing.assert_array_equal(read_pcd(p).points, np.ones((4, 3), np.float32))
    bad = tmp_path / "bad.pcd"
    _pcd_lzf(bad, 4, bytes([1 << 5, 9]) + b"x" * 10)  # a reference before the start
    with _raises_naming(bad, "corrupt binary_compressed"):
        read_pcd(bad)


def test_pcd_binary_compressed_written_by_pypcd4(tmp_path, rng):
    """A file as the library writes it (with real compression), and our writer's option."""
    from pypcd4 import Encoding, PointCloud

    a = _xyzi(rng, 3000)
    a[:1500] = a[0]
    p = tmp_path / "lib.pcd"
    PointCloud.from_xyzi_points(a).save(p, encoding=Encoding.BINARY_COMPRESSED)
    assert b"DATA binary_compressed" in p.read_bytes()[:400]
    s = read_pcd(p)
    np.testing.assert_array_equal(s.points, a[:, :3])
    np.testing.assert_array_equal(s.intensity, a[:, 3])
    q = write_pcd(tmp_path / "ours.pcd", s, compressed=True)
    assert b"DATA binary_compressed" in q.read_bytes()[:400]
    np.testing.assert_array_equal(read_pcd(q).points, a[:, :3])


def test_pcd_binary_compressed_open3d(tmp_path, rng):
    """Cross-check with Open3D's writer (real LZF compression with back references)."""
    o3d = pytest.importorskip("open3d")
    a = _xyzi(rng, 2000)
    a[:1000] = a[0]  # repetitive data so the compressor emits back references
    pcd = o3d.t.geometry.PointCloud()
    pcd.point.positions = o3d.core.Tensor(a[:, :3])
    pcd.point.intensity = o3d.core.Tensor(a[:, 3:4])
    p = tmp_path / "o3d.pcd"
    assert o3d.t.io.write_point_cloud(str(p), pcd, compressed=True)
    assert b"DATA binary_compressed" in p.read_bytes()[:400]
    s = read_pcd(p)
    np.testing.assert_array_equal(s.points, a[:, :3])
    np.testing.assert_array_equal(s.intensity, a[:, 3])


# ------------------------------------------------------------------------------- PLY


def test_ply_ascii_with_faces(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text(
        "ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 3\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar red\n"
        "property float scalar_Intensity\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
        "1 2 3 255 0.5\n4 5 6 0 1.5\n7 8 9 10 2.5\n3 0 1 2\n"
    )
    s = read_ply(p)
    np.testing.assert_array_equal(s.points, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    np.testing.assert_array_equal(s.intensity, [0.5, 1.5, 2.5])


@pytest.mark.parametrize("order", ["<", ">"])
def test_ply_binary(tmp_path, rng, order):
    n = 25
    dt = np.dtype([("nx", order + "f4"), ("z", order + "f8"), ("x", order + "f4"),
                   ("ring", order + "u2"), ("y", order + "f4")])  # fmt: skip
    rec = np.zeros(n, dtype=dt)
    xyz = rng.normal(size=(n, 3)).astype(np.float32)
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["ring"] = 7
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float nx\nproperty double z\n"
        "property float32 x\nproperty ushort ring\nproperty float y\nend_header\n"
    )
    p = tmp_path / "b.ply"
    p.write_bytes(header.encode() + rec.tobytes())
    s = read_scan(p)
    np.testing.assert_array_equal(s.points, xyz)
    assert s.intensity is None


def test_ply_vertex_not_first(tmp_path):
    p = tmp_path / "late.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\n"
        "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n1 2 3\n"
    )
    with _raises_naming(p, "vertex element must come first"):
        read_ply(p)


# ------------------------------------------------------------------------------- numpy


@pytest.mark.parametrize("cols", [3, 4, 6])
def test_npy(tmp_path, rng, cols):
    a = rng.normal(size=(20, cols))
    p = tmp_path / "s.npy"
    np.save(p, a)
    s = read_scan(p)
    np.testing.assert_allclose(s.points, a[:, :3].astype(np.float32))
    assert (s.intensity is None) == (cols == 3)


def test_npz_points_key(tmp_path, rng):
    a = rng.normal(size=(20, 3)).astype(np.float32)
    p = tmp_path / "s.npz"
    np.savez(p, points=a, intensity=np.arange(20), other=np.zeros(2))
    s = read_scan(p)
    np.testing.assert_array_equal(s.points, a)
    np.testing.assert_array_equal(s.intensity, np.arange(20))
    q = tmp_path / "bad.npz"
    np.savez(q, a=a, b=a)
    with _raises_naming(q, "points"):
        read_npy(q)


def test_scan_from_array_validation(tmp_path):
    with pytest.raises(InputError, match=r"\[5, 2\]"):
        scan_from_array(np.zeros((5, 2)))
    with pytest.raises(InputError, match="dtype"):
        scan_from_array(np.array([["a", "b", "c"]]))
    s = scan_from_array(np.array([[np.nan, 0, 0, 1], [1, 2, 3, 4]]))
    assert len(s) == 2 and s.points.dtype == np.float32
    p = tmp_path / "flat.npy"
    np.save(p, np.zeros(12))
    with _raises_naming(p, "[12]"):
        read_scan(p)


# ------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize(
    "writer,name",
    [
        (write_kitti_bin, "r.bin"),
        (lambda p, s: write_pcd(p, s, binary=True), "rb.pcd"),
        (lambda p, s: write_pcd(p, s, binary=False), "ra.pcd"),
        (lambda p, s: write_ply(p, s, binary=True), "rb.ply"),
        (lambda p, s: write_ply(p, s, binary=False), "ra.ply"),
    ],
)
def test_round_trip(tmp_path, rng, writer, name):
    a = _xyzi(rng, 200)
    a[:, :3] *= np.float32(1.0 / 3.0)  # values that need all float32 digits
    scan = Scan(a[:, :3], a[:, 3], "generated")
    p = tmp_path / name
    writer(p, scan)
    back = read_scan(p)
    np.testing.assert_array_equal(back.points, scan.points)
    np.testing.assert_array_equal(back.intensity, scan.intensity)


def test_pcd_round_trip_without_intensity(tmp_path, rng):
    pts = rng.normal(size=(10, 3)).astype(np.float32)
    p = write_pcd(tmp_path / "xyz.pcd", Scan(pts))
    assert b"FIELDS x y z\n" in p.read_bytes()
    back = read_pcd(p)
    np.testing.assert_array_equal(back.points, pts)
    assert back.intensity is None


# ------------------------------------------------------------------------------- bad files


def _binary_pcd_bytes(n_header: int, n_data: int) -> bytes:
    header = (
        "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH {n_header}\nHEIGHT 1\nPOINTS {n_header}\nDATA binary\n"
    )
    return header.encode() + np.ones((n_data, 4), "<f4").tobytes()


def test_truncated_binary_pcd(tmp_path):
    p = tmp_path / "trunc.pcd"
    p.write_bytes(_binary_pcd_bytes(100, 100)[:-7])
    with _raises_naming(p, "truncated", "100 points"):
        read_scan(p)


def test_pcd_wrong_point_count(tmp_path):
    p = tmp_path / "count.pcd"
    p.write_bytes(_binary_pcd_bytes(100, 10))
    with _raises_naming(p, "100 points", "160 bytes"):
        read_pcd(p)
    p2 = tmp_path / "more.pcd"
    p2.write_bytes(_binary_pcd_bytes(10, 100))
    with _raises_naming(p2, "10 points", "100 points"):
        read_pcd(p2)
    p3 = tmp_path / "count_ascii.pcd"
    lines = "".join(f"{k} 0 0 1\n" for k in range(10))
    p3.write_text(
        "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        f"WIDTH 100\nHEIGHT 1\nPOINTS 100\nDATA ascii\n{lines}"
    )
    with _raises_naming(p3, "100 points", "10 lines"):
        read_pcd(p3)
    p4 = tmp_path / "extra_ascii.pcd"
    p4.write_text(p3.read_text().replace("100", "5"))
    with _raises_naming(p4, "5 points", "10 lines"):
        read_pcd(p4)


@pytest.mark.parametrize("ext", [".pcd", ".ply", ".bin", ".npy", ".npz"])
def test_random_bytes(tmp_path, rng, ext):
    p = tmp_path / f"garbage{ext}"
    p.write_bytes(rng.integers(0, 256, size=1001, dtype=np.uint8).tobytes())
    with _raises_naming(p):
        read_scan(p)


@pytest.mark.parametrize(
    "header,problem",
    [
        ("FIELDS x y intensity\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n", "no z field"),
        ("FIELDS x y z\nSIZE 4 4\nTYPE F F F\nCOUNT 1 1 1\n", "SIZE has 2 entries"),
        ("FIELDS x y z\nSIZE 4 4 3\nTYPE F F F\nCOUNT 1 1 1\n", "unsupported TYPE F SIZE 3"),
        ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nFOO 1\n", "unknown key 'FOO'"),
        ("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 2 1\n", "'y' has COUNT 2"),
        ("", "the header has no FIELDS"),
        ("FIELDS x x y z\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n", "names a field twice"),
    ],
)
def test_pcd_bad_headers(tmp_path, header, problem):
    p = tmp_path / "bad.pcd"
    p.write_text(f"VERSION 0.7\n{header}WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n")
    with _raises_naming(p, problem):
        read_pcd(p)


def test_pcd_width_height_points_mismatch(tmp_path):
    p = tmp_path / "wh.pcd"
    p.write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 2\nPOINTS 3\nDATA ascii\n")
    with _raises_naming(p, "WIDTH 2 x HEIGHT 2 != POINTS 3"):
        read_pcd(p)
    q = tmp_path / "wtext.pcd"
    q.write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH abc\nDATA ascii\n1 2 3\n")
    with _raises_naming(q, "not a valid PCD header", "'abc'"):
        read_pcd(q)


def test_ply_errors(tmp_path):
    no_x = tmp_path / "nox.ply"
    no_x.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nproperty float z\n"
        "end_header\n1 2\n"
    )
    with _raises_naming(no_x, "no x field"):
        read_scan(no_x)
    short = tmp_path / "short.ply"
    short.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + b"\x00" * 50
    )
    with _raises_naming(short, "truncated", "10 vertices"):
        read_scan(short)
    bad_line = tmp_path / "line.ply"
    bad_line.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n1 2 3\n4 5\n"
    )
    with _raises_naming(bad_line, "line 9 has 2 values"):
        read_scan(bad_line)
    head = "ply\nformat {} 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
    head += "property float z\nend_header\n"
    fewer = tmp_path / "fewer.ply"  # the header says 2 vertices, 3 follow
    fewer.write_text(head.format("ascii") + "1 2 3\n4 5 6\n7 8 9\n")
    with _raises_naming(fewer, "says 2 vertices but 1 more line(s) follow"):
        read_scan(fewer)
    fewer_bin = tmp_path / "fewer-bin.ply"
    data = np.arange(9, dtype="<f4").tobytes()
    fewer_bin.write_bytes(head.format("binary_little_endian").encode() + data)
    with _raises_naming(fewer_bin, "says 2 vertices but 12 more byte(s) follow"):
        read_scan(fewer_bin)
    listed = tmp_path / "list.ply"
    listed.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\n"
        "property float y\nproperty float z\nend_header\n2 1 2 3 4\n"
    )
    with _raises_naming(listed, "'x' is a list"):
        read_scan(listed)


def test_a_corrupt_npz_names_the_file(tmp_path, rng):
    """A damaged zip member (bad CRC) or a file that is no zip at all."""
    good = tmp_path / "good.npz"
    np.savez(good, points=rng.normal(size=(50, 3)).astype(np.float32))
    raw = bytearray(good.read_bytes())
    raw[raw.find(b"\x93NUMPY") + 130] ^= 0xFF
    crc = tmp_path / "crc.npz"
    crc.write_bytes(bytes(raw))
    with _raises_naming(crc, "CRC"):
        read_scan(crc)
    nozip = tmp_path / "nozip.npz"
    nozip.write_bytes(b"PK\x03\x04" + b"\0" * 40)
    with _raises_naming(nozip, "not a zip file"):
        read_scan(nozip)


def test_missing_and_unknown(tmp_path):
    missing = tmp_path / "nothere.pcd"
    with _raises_naming(missing, "not found"):
        read_scan(missing)
    unknown = tmp_path / "scan.las"
    unknown.write_bytes(b"x")
    with _raises_naming(unknown, "unknown scan file extension"):
        read_scan(unknown)


# ------------------------------------------------------------------------------- poses


def _random_pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, rng.normal(size=3) * 5
    return T


def test_relative_pose(rng):
    Ti, Tj = _random_pose(rng), _random_pose(rng)
    T_j_i = relative_pose(Ti, Tj)
    np.testing.assert_allclose(T_j_i, np.linalg.inv(Tj) @ Ti, atol=1e-12)
    # a world point seen from i, mapped into j, is the same world point seen from j
    p_world = np.array([1.0, -2.0, 3.0, 1.0])
    p_i = np.linalg.inv(Ti) @ p_world
    np.testing.assert_allclose(T_j_i @ p_i, np.linalg.inv(Tj) @ p_world, atol=1e-12)
    np.testing.assert_allclose(relative_pose(Ti, Ti), np.eye(4), atol=1e-12)
    with pytest.raises(InputError):
        relative_pose(np.eye(3), Tj)


def test_read_poses_errors(tmp_path):
    ok = "1 0 0 1 0 1 0 2 0 0 1 3\n"
    p = tmp_path / "poses.txt"
    p.write_text(ok + "1 0 0 1 0 1 0 2 0 0 1\n")
    with _raises_naming(p, "line 2 has 11 values"):
        read_poses(p)
    p.write_text(ok + ok + "1 0 0 1 0 1 0 x 0 0 1 3\n")
    with _raises_naming(p, "line 3"):
        read_poses(p)
    p.write_text("2 0 0 1 0 1 0 2 0 0 1 3\n")
    with _raises_naming(p, "line 1", "not a rotation"):
        read_poses(p)
    p.write_text(ok + "\n" + ok)
    T = read_poses(p)
    assert T.shape == (2, 4, 4)
    np.testing.assert_array_equal(T[1, :3, 3], [1, 2, 3])


# ------------------------------------------------------------------------------- fixture


def test_fixture_sequence(balm_mini_dir, balm_mini_roles):
    seq = KittiSequence(balm_mini_dir)
    assert len(seq) == 15 == len(balm_mini_roles)
    assert seq.poses.shape == (15, 4, 4) and seq.poses.dtype == np.float64
    R = seq.poses[:, :3, :3]  # [F, 3, 3]
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-4
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-4)
    np.testing.assert_array_equal(seq.poses[:, 3], np.broadcast_to([0, 0, 0, 1], (15, 4)))
    assert np.all(np.diff(seq.times) > 0)
    roles = [r for _, r in balm_mini_roles]
    assert roles.count("query") == 3 and roles[-3:] == ["query"] * 3
    frames = list(seq)
    assert [f.index for f in frames] == list(range(15))
    assert frames[1].path.name == "000001.bin" and frames[-1].index == 14
    scan = frames[0].scan()
    assert 5000 < len(scan) < 20000 and scan.intensity is not None
    assert np.linalg.norm(scan.points, axis=1).max() <= 40.0 + 1e-4


def test_fixture_pair_0_30(balm_mini_dir, balm_mini_roles):
    """Source scans 0 and 30: ~1.1 m apart, ~77 deg yaw change (source README)."""
    seq = KittiSequence(balm_mini_dir)
    i, j = [k for k, (orig, _) in enumerate(balm_mini_roles) if orig in (0, 30)]
    T_j_i = relative_pose(seq[i].T_world_sensor, seq[j].T_world_sensor)
    assert 0.9 < np.linalg.norm(T_j_i[:3, 3]) < 1.3
    yaw = np.degrees(np.arctan2(T_j_i[1, 0], T_j_i[0, 0]))
    assert 70 < abs(yaw) < 85


@pytest.mark.parametrize("i,j", [(0, 1), (12, 0), (13, 11), (14, 11)])
def test_fixture_poses_align_scans(balm_mini_dir, i, j):
    """The README's pairs: scan i mapped by inv(T_world_j) @ T_world_i lands on scan j."""
    from scipy.spatial import cKDTree

    seq = KittiSequence(balm_mini_dir)
    a, b = seq[i], seq[j]
    pa, pb = a.scan().points.astype(np.float64), b.scan().points.astype(np.float64)
    T_b_a = relative_pose(a.T_world_sensor, b.T_world_sensor)
    tree = cKDTree(pb)
    aligned = tree.query(pa @ T_b_a[:3, :3].T + T_b_a[:3, 3])[0]  # [Pa]
    wrong = tree.query(pa @ T_b_a[:3, :3] + T_b_a[:3, 3])[0]  # transposed rotation
    assert np.median(aligned) < 0.3
    assert np.median(aligned) < 0.3 * np.median(wrong)


def _copy_fixture(src: Path, dst: Path, n: int = 4) -> Path:
    (dst / "velodyne").mkdir(parents=True)
    for k in range(n):
        shutil.copy(src / "velodyne" / f"{k:06d}.bin", dst / "velodyne")
    for name in ("poses.txt", "times.txt"):
        lines = (src / name).read_text().splitlines()[:n]
        (dst / name).write_text("\n".join(lines) + "\n")
    return dst


def test_sequence_count_mismatch(tmp_path, balm_mini_dir):
    root = _copy_fixture(balm_mini_dir, tmp_path / "seq")
    assert len(KittiSequence(root)) == 4
    poses = root / "poses.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:3]) + "\n")
    with _raises_naming(poses, "3 poses", "4 scans"):
        KittiSequence(root)


def test_sequence_times_and_optional_files(tmp_path, balm_mini_dir):
    root = _copy_fixture(balm_mini_dir, tmp_path / "seq")
    times = root / "times.txt"
    lines = times.read_text().splitlines()
    times.write_text("\n".join(lines[:2] + ["oops"] + lines[3:]) + "\n")
    with _raises_naming(times, "line 3"):
        KittiSequence(root)
    times.write_text("\n".join(lines[:3]) + "\n")
    with _raises_naming(times, "3 times", "4 scans"):
        KittiSequence(root)
    times.unlink()
    (root / "poses.txt").unlink()
    seq = KittiSequence(root)
    assert seq.poses is None and seq[2].time is None and seq[2].T_world_sensor is None
    assert len(seq[-1].scan()) > 0
    with pytest.raises(IndexError):
        seq[4]


def test_sequence_pcd_scans_dir(tmp_path, rng):
    root = tmp_path / "seq"
    (root / "scans").mkdir(parents=True)
    for k in range(3):
        write_pcd(root / "scans" / f"{k:04d}.pcd", scan_from_array(_xyzi(rng, 5 + k)))
    seq = KittiSequence(root)
    assert [len(f.scan()) for f in seq] == [5, 6, 7]
    empty = tmp_path / "empty"
    empty.mkdir()
    with _raises_naming(empty, "no velodyne/ or scans/"):
        KittiSequence(empty)


def test_a_ply_list_intensity_is_left_out(tmp_path):
    """Only x, y and z must be numbers; an intensity that is a list is not one to read."""
    p = tmp_path / "list-intensity.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty list uchar float intensity\nend_header\n"
        "1 2 3 2 4 5\n4 5 6 1 7\n"
    )
    scan = read_scan(p)
    assert scan.points.tolist() == [[1, 2, 3], [4, 5, 6]] and scan.intensity is None


def test_a_pcd_may_pad_with_several_underscore_fields(tmp_path):
    """PCL's padding fields are all named "_" (Ouster's layout has several): not a field
    named twice."""
    rec = np.zeros(2, dtype=[(n, "<f4") for n in ("x", "y", "z", "p1", "intensity", "p2")])
    rec["x"], rec["y"], rec["z"], rec["intensity"] = [1, 4], [2, 5], [3, 6], [0.5, 0.25]
    head = (
        "VERSION .7\nFIELDS x y z _ intensity _\nSIZE 4 4 4 4 4 4\nTYPE F F F F F F\n"
        "COUNT 1 1 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA binary\n"
    )
    p = tmp_path / "padded.pcd"
    p.write_bytes(head.encode() + rec.tobytes())
    scan = read_scan(p)
    assert scan.points.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert scan.intensity.tolist() == [0.5, 0.25]
    twice = tmp_path / "twice.pcd"
    twice.write_bytes(head.replace("x y z _ intensity _", "x y z x intensity _").encode())
    with _raises_naming(twice, "names a field twice"):
        read_scan(twice)
