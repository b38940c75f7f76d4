"""Map archives through the map manager: exact round trip, and refusal of damaged,
truncated and foreign archives without leaving anything behind."""

from __future__ import annotations

import hashlib
import io
import tarfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from svc_helpers import random_features
from test_store import SPEC, _items, _manager

from sgvloc.core.errors import ConflictError, EncoderMismatchError, InputError, NotFoundError
from sgvloc.server import archive
from sgvloc.server.archive import ArchiveError
from sgvloc.server.maps import LOCK_NAME, FeaturesIn, MapManager


def _export(m: MapManager, name: str) -> bytes:
    with m.export_archive(name) as blocks:
        return b"".join(blocks)


def _answer(m: MapManager, name: str, q: FeaturesIn) -> tuple:
    r = m.localize(name, features=q, top_k=10, rerank="sgv", min_confidence=0.0)
    return (
        r.map_version,
        [(c.keyframe_id, round(c.similarity, 6)) for c in r.retrieved],
        [(c.keyframe_id, round(c.score, 6)) for c in r.reranked],
        r.keyframe_id,
        None if r.T_map_sensor_estimate is None else np.round(r.T_map_sensor_estimate, 9).tolist(),
        round(r.confidence, 9),
    )


@pytest.fixture
def source(tmp_path: Path) -> MapManager:
    rng = np.random.default_rng(11)
    m = _manager(tmp_path / "a")
    m.create("src", SPEC, self_test={"chosen": "egonn", "figures": [{"recall_at_1": 93.0}]})
    ids = m.insert("src", _items(rng, 300, "k")).ids  # two archive chunks
    m.delete_keyframe("src", ids[5])
    m.insert("src", _items(rng, 3))  # keyless ones too
    m.update_settings("src", {"top_k": 7})
    m.record_self_test("src", {"figures": {"recall_at_1": 90.0}})  # a settings change too
    yield m
    m.close()


def test_round_trip_is_exact(source: MapManager, tmp_path: Path) -> None:
    data = _export(source, "src")
    dest = _manager(tmp_path / "b")
    h = dest.import_archive(io.BytesIO(data))
    assert h.name == "src"
    dest.import_archive(io.BytesIO(data), "copy")
    a, b = source.get("src"), dest.get("copy")
    assert (b.version, b.num_keyframes) == (a.version, a.num_keyframes) == (3, 302)
    assert b.record == replace(a.record, name="copy")  # the self-tests too
    assert b.record.self_test["chosen"] == "egonn" and b.record.last_self_test is not None
    assert b.record.settings_version == 2 and b.record.localizer_config.top_k == 7
    with a.store.snapshot() as (_, _, rows):
        rows_a = list(rows)
    with b.store.snapshot() as (_, _, rows):
        rows_b = list(rows)
    assert [r.id for r in rows_a] == [r.id for r in rows_b]
    for x, y in zip(rows_a, rows_b, strict=True):
        assert (x.key, x.metadata, x.created_at) == (y.key, y.metadata, y.created_at)
        for f in ("T_map_sensor", "global_descriptor", "keypoints", "local_features"):
            np.testing.assert_array_equal(getattr(x, f), getattr(y, f))
    rng = np.random.default_rng(3)
    for _ in range(5):
        f = random_features(rng)
        q = FeaturesIn(f["global_descriptor"], f["keypoints"], f["local_features"])
        assert _answer(source, "src", q) == _answer(dest, "copy", q)
    # the import survives a restart like any map
    dest.close()
    again = _manager(tmp_path / "b")
    assert again.get("copy").num_keyframes == 302 and again.failed == {}
    with pytest.raises(ConflictError):
        again.import_archive(io.BytesIO(data), "copy")
    again.close()


def _members(data: bytes) -> list[tuple[str, bytes]]:
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        return [(i.name, tar.extractfile(i).read()) for i in tar]


def _tar(members: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _refused(m: MapManager, data: bytes, match: str, error=ArchiveError) -> None:
    with pytest.raises(error, match=match):
        m.import_archive(io.BytesIO(data), "imported")
    assert [p.name for p in m.maps_dir.iterdir()] == [LOCK_NAME]  # nothing left behind
    with pytest.raises(NotFoundError):
        m.get("imported")


def test_damaged_truncated_and_foreign_archives_are_refused(
    source: MapManager, tmp_path: Path
) -> None:
    data = _export(source, "src")
    m = _manager(tmp_path / "c")
    members = _members(data)
    assert [n for n, _ in members] == [
        "manifest.json",
        "keyframes/000000.npz",
        "keyframes/000001.npz",
        "SHA256SUMS",
    ]
    # one flipped byte inside the features of a chunk
    name, chunk = members[2]
    flipped = (
        chunk[: len(chunk) // 2]
        + bytes([chunk[len(chunk) // 2] ^ 1])
        + chunk[len(chunk) // 2 + 1 :]
    )
    _refused(m, _tar([*members[:2], (name, flipped), members[3]]), "damaged")
    _refused(m, data[: len(data) // 2], "truncated|damaged")
    _refused(m, _tar(members[:3]), "no SHA256SUMS")
    _refused(m, b"\x00" * 4096, "not an sgvloc map archive")
    _refused(m, b"plain text, not a tar file at all", "not an sgvloc map archive")
    _refused(m, _tar([("README", b"hi"), *members]), "first member is not manifest.json")
    _refused(
        m,
        _tar([("manifest.json", b'{"format": "zip", "format_version": 1}'), *members[1:]]),
        "not an sgvloc map archive",
    )
    _refused(
        m,
        _tar(
            [
                (
                    "manifest.json",
                    members[0][1].replace(b'"format_version": 2', b'"format_version": 9'),
                ),
                *members[1:],
            ]
        ),
        "format version 9 is not supported",
    )
    truth = members[0][1].replace(b'"format_version": 2', b'"format_version": true')
    _refused(m, _tar([("manifest.json", truth), *members[1:]]), "format version True")
    assert m.import_archive(io.BytesIO(data), "imported").num_keyframes == 302  # name free
    # the archives of earlier releases (version 1) are read too
    v1 = members[0][1].replace(b'"format_version": 2', b'"format_version": 1')
    old_sum = hashlib.sha256(members[0][1]).hexdigest().encode()
    sums = members[3][1].replace(old_sum, hashlib.sha256(v1).hexdigest().encode())
    assert sums != members[3][1]
    v1_archive = _tar([("manifest.json", v1), *members[1:3], ("SHA256SUMS", sums)])
    assert m.import_archive(io.BytesIO(v1_archive), "v1").num_keyframes == 302
    m.close()


def test_extended_tar_headers_are_bounded(source: MapManager, tmp_path: Path) -> None:
    """An extended tar header (pax, GNU long name) over 8 KiB is refused before tarfile
    reads it whole (an attacker's declared size) or parses it (quadratic on some
    Pythons); a re-packed archive with short pax records imports as before."""
    data = _export(source, "src")
    m = _manager(tmp_path / "x")
    members = _members(data)

    def with_extended(kind: bytes, payload: bytes) -> bytes:
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
            info = tarfile.TarInfo("header")
            info.type, info.size = kind, len(payload)
            tar.addfile(info, io.BytesIO(payload))
        return buf.getvalue()

    _refused(m, with_extended(tarfile.XHDTYPE, b"1" * 100_000), "extended tar header of 100000 B")
    _refused(m, with_extended(tarfile.GNUTYPE_LONGNAME, b"a" * 9000), "extended tar header")
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for name, payload in members:
            info = tarfile.TarInfo(name)
            info.size = len(payload)
            info.pax_headers = {"comment": "re-packed by another tool"}
            tar.addfile(info, io.BytesIO(payload))
    assert m.import_archive(io.BytesIO(buf.getvalue()), "repacked").num_keyframes == 302
    m.close()


def test_an_archive_of_another_encoder_is_refused(source: MapManager, tmp_path: Path) -> None:
    h = source.get("src")
    with h.store.snapshot() as (version, count, rows):
        foreign = replace(h.record, encoder_fingerprint="0" * 16)
        data = b"".join(archive.write_archive(foreign, version, count, rows))
    m = _manager(tmp_path / "d")
    _refused(m, data, "fingerprint", EncoderMismatchError)
    m.close()


def _tampered(members: list[tuple[str, bytes]], arrays=None, manifest=None, compress=False):
    """The archive with its first chunk's arrays (``arrays(dict)``) and its manifest
    (``manifest(dict)``) changed and the checksums made to match: well-formed, hostile."""
    import hashlib
    import json

    out = []
    for name, data in members:
        if name == "manifest.json" and manifest is not None:
            m = json.loads(data)
            manifest(m)
            data = json.dumps(m).encode()
        if name == "keyframes/000000.npz" and (arrays is not None or compress):
            with np.load(io.BytesIO(data)) as z:
                a = {k: z[k] for k in z.files}
            if arrays is not None:
                arrays(a)
            buf = io.BytesIO()
            (np.savez_compressed if compress else np.savez)(buf, **a)
            data = buf.getvalue()
        if name == "SHA256SUMS":
            data = "".join(f"{hashlib.sha256(d).hexdigest()}  {n}\n" for n, d in out).encode()
        out.append((name, data))
    return _tar(out)


def _records(edit):
    import json

    def change(a: dict) -> None:
        recs = json.loads(a["records"].tobytes())
        edit(recs[0])
        a["records"] = np.frombuffer(json.dumps(recs).encode(), dtype=np.uint8)

    return change


def test_a_well_formed_but_hostile_archive_is_refused(source: MapManager, tmp_path: Path) -> None:
    """Checksums only say an archive was not damaged on its way: its content is checked
    as an insert's is. Each of these was imported and then answered 500s (or inflated
    to gigabytes) before."""
    members = _members(_export(source, "src"))
    m = _manager(tmp_path / "d")

    def cloud(values):
        def change(a: dict) -> None:
            a["cloud_counts"] = a["cloud_counts"].copy()
            a["cloud_counts"][0] = len(values)
            a["clouds"] = np.asarray(values, np.float32).reshape(len(values), -1)

        return change

    def pose(a: dict) -> None:
        a["T_map_sensor"] = a["T_map_sensor"].copy()
        a["T_map_sensor"][0, 0, 3] = 1e200

    def setting(key, value):
        def change(mf: dict) -> None:
            (mf["map"] if key in mf["map"] else mf)[key] = value

        return change

    cases = [
        (_tampered(members, compress=True), "compressed"),
        (_tampered(members, cloud([[np.nan, 0, 0], [1, 2, 3]])), "cloud"),
        (_tampered(members, cloud([[1e30, 0, 0]])), "cloud"),
        (_tampered(members, cloud([[1, 2], [3, 4]])), "cloud"),
        (_tampered(members, pose), "translation"),
        (_tampered(members, _records(lambda r: r.update(key="\ud800"))), "surrogate"),
        (_tampered(members, _records(lambda r: r.update(key="x" * 300))), "key"),
        (
            _tampered(members, _records(lambda r: r["metadata"].update(timestamp=float("nan")))),
            "metadata",
        ),
        (_tampered(members, _records(lambda r: r.update(metadata={"tags": [1]}))), "tags"),
        (_tampered(members, manifest=setting("version", 2**70)), "out of range"),
        (_tampered(members, manifest=setting("settings_version", 2**70)), "out of range"),
        (_tampered(members, manifest=setting("self_test", {"x": "y" * 300_000})), "self_test"),
        # stored as given and served back before: the API refuses each of these
        (_tampered(members, manifest=setting("self_test", {"x": float("nan")})), "not finite"),
        (_tampered(members, manifest=setting("self_test", {"x": "a\x00"})), "NUL"),
        (_tampered(members, manifest=setting("settings_updated_at", {"a": 1})), "ISO 8601"),
        (_tampered(members, manifest=setting("created_at", "x" * 100_000)), "ISO 8601"),
        (_tampered(members, manifest=setting("keep_clouds", "false")), "keep_clouds"),
        (_tampered(members, _records(lambda r: r.update(created_at=12345))), "ISO 8601"),
    ]
    for data, match in cases:
        _refused(m, data, match)
    if not torch.cuda.is_available():  # settings this machine cannot run: refused at once

        def cuda(mf: dict) -> None:
            mf["map"]["localizer_config"].setdefault("sgv", {})["device"] = "cuda"

        _refused(m, _tampered(members, manifest=cuda), "localizer.sgv", InputError)
    assert m.import_archive(io.BytesIO(_tampered(members)), "imported").num_keyframes == 302
    m.close()
