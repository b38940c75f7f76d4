"""A synthetic town and a simulated LiDAR drive through it, written in the KITTI layout.

The town is a grid of square blocks separated by streets. It is built to be hard for
place recognition on purpose: every block copies one of a few **templates** (the same
building footprints and heights, only turned by a multiple of 90 degrees), streets carry
poles at a fixed spacing and parked cars in regular slots, so many places look alike.

The drive is a random walk over the street grid (no U-turns), followed by the same walk
backwards, so every street of the first half is **revisited from the opposite
direction**; each street traversal picks one of two lanes at random, so revisits also come
with **lane offsets** (right-hand traffic; the opposite direction is also one road half
over). The walk itself revisits streets in the same direction now and then.

The LiDAR is simulated by ray casting (Open3D ``RaycastingScene``): ``beams`` rings over a
vertical field of view, ``azimuth_steps`` rays per ring with a random azimuth phase per
scan, Gaussian range noise, random dropouts and a range limit. ``fov_h_deg`` narrows the
horizontal field of view about the forward axis and ``pattern="rosette"`` replaces the
rings by a non-repetitive petal pattern, as forward-looking solid-state sensors have. Intensity is a
per-material reflectivity times the cosine of the incidence angle, plus noise.

Output (KITTI odometry layout): ``velodyne/NNNNNN.bin`` (float32 x y z intensity, sensor
frame), ``poses.txt`` (row-major top 3x4 of ``T_world_sensor``), ``times.txt`` and
``synth.json`` (the configuration and a summary). Everything derives from ``seed``: the
same configuration writes the same bytes.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from sgvloc.core.errors import InputError
from sgvloc.core.o3d import open3d

from .staging import staged

log = logging.getLogger(__name__)

#: material classes of the town's meshes and their reflectivity (intensity scale)
MATERIALS = {"ground": 0.25, "building": 0.55, "pole": 0.85, "car": 0.7, "tree": 0.35}
#: lane centres, metres to the right of the street centreline (two lanes per direction)
LANES = (1.75, 5.25)


class SynthConfig(BaseModel):
    """Parameters of the town, the drive and the LiDAR (all recorded in ``synth.json``)."""

    model_config = ConfigDict(extra="forbid")

    scans: int = Field(400, ge=1, description="number of scans")
    seed: int = 0
    # the town
    templates: int = Field(3, ge=1, description="distinct block layouts, repeated everywhere")
    block_m: float = Field(44.0, ge=20.0, description="block side (m)")
    street_m: float = Field(20.0, ge=12.0, description="street width, kerb to kerb (m)")
    pole_spacing_m: float = Field(20.0, gt=0.0)
    car_slot_m: float = Field(7.0, gt=4.5, description="parking slot length (m)")
    car_probability: float = Field(0.45, ge=0.0, le=1.0, description="a slot is occupied")
    grid: int | None = Field(None, ge=1, description="blocks per side (default: from the route)")
    # the drive
    step_m: float = Field(1.0, gt=0.0, description="distance between scans (m)")
    rate_hz: float = Field(10.0, gt=0.0, description="scans per second (sets times.txt)")
    sensor_height_m: float = Field(1.8, gt=0.0)
    tilt_deg: float = Field(0.5, ge=0.0, description="amplitude of roll/pitch wobble")
    # the LiDAR
    pattern: Literal["spinning", "rosette"] = Field(
        "spinning",
        description="spinning: beams rings swept in azimuth; rosette: a non-repetitive "
        "petal pattern over the field of view, turned per scan (solid-state sensors)",
    )
    beams: int = Field(32, ge=8, le=128)
    azimuth_steps: int = Field(
        1024, ge=64, le=8192, description="rays per ring over 360 deg (rosette: per beam)"
    )
    fov_h_deg: float = Field(
        360.0,
        gt=0.0,
        le=360.0,
        description="horizontal field of view about the forward axis (+x); below 360 the "
        "spinning pattern keeps its azimuth spacing, so scans hold fewer points",
    )
    fov_up_deg: float = Field(15.0, ge=-90.0, le=90.0)
    fov_down_deg: float = Field(-25.0, ge=-90.0, le=90.0)
    min_range_m: float = Field(1.0, ge=0.0)
    max_range_m: float = Field(80.0, gt=0.0)
    range_noise_m: float = Field(0.02, ge=0.0, description="Gaussian range noise sigma")
    dropout: float = Field(0.05, ge=0.0, lt=1.0, description="share of returns lost")
    intensity_noise: float = Field(0.03, ge=0.0)

    @model_validator(mode="after")
    def _vertical_fov(self) -> SynthConfig:
        if self.fov_down_deg >= self.fov_up_deg:
            raise ValueError(
                f"fov_down_deg ({self.fov_down_deg}) must be below fov_up_deg ({self.fov_up_deg})"
            )
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})"
            )
        return self


# --------------------------------------------------------------------------------------
# The town


@dataclass
class Town:
    """Triangle meshes per material, in world coordinates (metres, z up)."""

    meshes: dict[str, tuple[np.ndarray, np.ndarray]]  # name -> (vertices [V, 3], tris [T, 3])
    grid: int
    pitch: float  # distance between parallel street centrelines
    stats: dict[str, int]


class _MeshBuilder:
    """Accumulates transformed copies of unit primitives into one vertex/triangle list."""

    def __init__(self) -> None:
        o3d = open3d()

        box = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)  # [0, 1]^3
        cyl = o3d.geometry.TriangleMesh.create_cylinder(radius=1.0, height=1.0, resolution=10)
        sph = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=5)
        self.unit = {
            "box": (np.asarray(box.vertices) - [0.5, 0.5, 0.0], np.asarray(box.triangles)),
            "cyl": (np.asarray(cyl.vertices) + [0.0, 0.0, 0.5], np.asarray(cyl.triangles)),
            "sph": (np.asarray(sph.vertices), np.asarray(sph.triangles)),
        }
        self.verts: list[np.ndarray] = []
        self.tris: list[np.ndarray] = []
        self.count = 0
        self._nv = 0

    def add(self, kind: str, center: tuple, size: tuple, yaw: float = 0.0) -> None:
        """A primitive scaled by ``size`` (x, y, z), turned by ``yaw``, base at ``center``."""
        v, t = self.unit[kind]
        c, s = math.cos(yaw), math.sin(yaw)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        vv = (v * np.asarray(size)) @ R.T + np.asarray(center)  # [V, 3]
        self.verts.append(vv)
        self.tris.append(t + self._nv)
        self._nv += len(vv)
        self.count += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.verts:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        return np.concatenate(self.verts), np.concatenate(self.tris)


def _block_template(rng: np.random.Generator, block: float) -> list[tuple]:
    """One block layout: (kind, material, center xy in block-local coords, size, yaw)."""
    items: list[tuple] = []
    half = block / 2.0
    setback = 3.0
    # 2 x 2 lots; each holds a building (one of a few footprints) or an open yard with trees
    for qx in (-1, 1):
        for qy in (-1, 1):
            lot = half - setback  # lot side
            if rng.random() < 0.8:
                w = rng.choice([0.55, 0.75, 0.9]) * lot
                d = rng.choice([0.5, 0.7, 0.9]) * lot
                h = float(rng.choice([6.0, 9.0, 12.0, 18.0]))
                # buildings stand at the street side of their lot
                cx = qx * (half - setback - w / 2.0)
                cy = qy * (half - setback - d / 2.0)
                items.append(("box", "building", (cx, cy), (w, d, h), 0.0))
                if rng.random() < 0.5:  # an annex: L-shaped footprint
                    aw, ad = w * 0.4, d * 0.6
                    ax = cx - qx * (w / 2.0 + aw / 2.0)
                    ay = cy - qy * (d - ad) / 2.0
                    items.append(("box", "building", (ax, ay), (aw, ad, h * 0.5), 0.0))
            else:
                for _ in range(int(rng.integers(2, 5))):
                    tx = qx * rng.uniform(4.0, lot - 2.0)
                    ty = qy * rng.uniform(4.0, lot - 2.0)
                    items.append(("tree", "tree", (tx, ty), (0.25, 0.25, 3.0), 0.0))
    return items


def build_town(cfg: SynthConfig, grid: int) -> Town:
    """The meshes of a town whose driven streets form a ``grid`` x ``grid`` block grid
    (street centrelines at multiples of ``pitch = block_m + street_m`` from 0 to
    ``grid * pitch``), with one more ring of blocks around it."""
    rng = np.random.default_rng([cfg.seed, 1])
    pitch = cfg.block_m + cfg.street_m
    builders = {m: _MeshBuilder() for m in MATERIALS}
    templates = [_block_template(rng, cfg.block_m) for _ in range(cfg.templates)]

    # ground: one quad under the whole town plus a margin beyond the LiDAR range
    lo, hi = -pitch - cfg.max_range_m, (grid + 1) * pitch + cfg.max_range_m
    span = hi - lo
    builders["ground"].add("box", ((lo + hi) / 2, (lo + hi) / 2, -0.1), (span, span, 0.1))

    # blocks: a template turned by a multiple of 90 degrees; one ring of blocks beyond the
    # driven streets so that the town's edge never looks onto empty land
    for bi in range(-1, grid + 1):
        for bj in range(-1, grid + 1):
            ox, oy = (bi + 0.5) * pitch, (bj + 0.5) * pitch  # block centre
            tpl = templates[int(rng.integers(len(templates)))]
            turn = int(rng.integers(4)) * (math.pi / 2)
            c, s = math.cos(turn), math.sin(turn)
            for kind, mat, (x, y), size, yaw in tpl:
                wx, wy = ox + c * x - s * y, oy + s * x + c * y
                if kind == "tree":
                    builders[mat].add("cyl", (wx, wy, 0.0), size)
                    builders[mat].add("sph", (wx, wy, 3.8), (1.8, 1.8, 1.5))
                else:
                    builders[mat].add(kind, (wx, wy, 0.0), size, yaw + turn)

    # streets: poles on the sidewalks, parked cars in the kerb lane
    kerb = cfg.street_m / 2.0
    for line in range(-1, grid + 2):
        for seg in range(-1, grid + 1):
            a = seg * pitch + kerb  # street segment between two intersections
            b = (seg + 1) * pitch - kerb
            for side in (-1.0, 1.0):
                off = line * pitch + side * (kerb + 0.6)
                for u in np.arange(a + 2.0, b, cfg.pole_spacing_m):
                    for horizontal in (True, False):
                        p = (u, off) if horizontal else (off, u)
                        builders["pole"].add("cyl", (*p, 0.0), (0.15, 0.15, 6.0))
                coff = line * pitch + side * (kerb - 1.1)
                for u in np.arange(a + cfg.car_slot_m / 2, b - cfg.car_slot_m / 2, cfg.car_slot_m):
                    for horizontal in (True, False):
                        if rng.random() >= cfg.car_probability:
                            continue
                        p = (u, coff) if horizontal else (coff, u)
                        yaw = 0.0 if horizontal else math.pi / 2
                        builders["car"].add("box", (*p, 0.25), (4.4, 1.8, 0.9), yaw)
                        builders["car"].add("box", (*p, 1.15), (2.4, 1.6, 0.55), yaw)
    meshes = {m: b.arrays() for m, b in builders.items()}
    stats = {m: b.count for m, b in builders.items()}
    return Town(meshes, grid, pitch, stats)


# --------------------------------------------------------------------------------------
# The drive


def _walk(rng: np.random.Generator, grid: int, edges: int) -> list[tuple[int, int]]:
    """A random walk of ``edges`` steps over the street intersections, never turning back."""
    node = (int(rng.integers(grid + 1)), int(rng.integers(grid + 1)))
    path = [node]
    prev = None
    for _ in range(edges):
        nbrs = [
            (node[0] + dx, node[1] + dy)
            for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1))
            if 0 <= node[0] + dx <= grid and 0 <= node[1] + dy <= grid
        ]
        choices = [n for n in nbrs if n != prev] or nbrs
        prev, node = node, choices[int(rng.integers(len(choices)))]
        path.append(node)
    return path


def _route_polyline(cfg: SynthConfig, grid: int, pitch: float, fwd_edges: int) -> np.ndarray:
    """Waypoints ``[W, 2]`` of a walk of ``fwd_edges`` streets and the way back, in lanes."""
    rng = np.random.default_rng([cfg.seed, 2])
    nodes = _walk(rng, grid, fwd_edges)
    nodes = nodes + nodes[-2::-1]  # back the same way: the opposite direction
    cut = min(0.3 * pitch, cfg.street_m / 2.0 + 2.0)  # corners are cut this far from the node
    pts: list[np.ndarray] = []
    for a, b in zip(nodes[:-1], nodes[1:], strict=True):
        pa, pb = np.array(a, float) * pitch, np.array(b, float) * pitch
        d = (pb - pa) / pitch
        right = np.array([d[1], -d[0]])
        lane = LANES[int(rng.integers(len(LANES)))]
        pts += [pa + d * cut + right * lane, pb - d * cut + right * lane]
    return np.stack(pts)


def route_poses(cfg: SynthConfig, grid: int, pitch: float) -> np.ndarray:
    """``[scans, 4, 4]`` T_world_sensor: a random walk and its way back, one pose per step."""
    length = cfg.scans * cfg.step_m + 4.0
    fwd_edges = max(1, math.ceil(length / pitch / 2.0))
    while True:  # cut corners shorten the route: add streets until it is long enough
        poly = _route_polyline(cfg, grid, pitch, fwd_edges)  # [W, 2]
        seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(seg)])  # [W]
        if arc[-1] >= length:
            break
        fwd_edges += 1
    s = np.arange(cfg.scans) * cfg.step_m
    xy = np.stack([np.interp(s, arc, poly[:, 0]), np.interp(s, arc, poly[:, 1])], axis=1)
    # heading from points 2 m ahead and behind: smooth through the cut corners
    ahead = np.stack([np.interp(s + 2.0, arc, poly[:, k]) for k in (0, 1)], axis=1)
    behind = np.stack([np.interp(np.maximum(s - 2.0, 0.0), arc, poly[:, k]) for k in (0, 1)], 1)
    d = ahead - behind
    yaw = np.arctan2(d[:, 1], d[:, 0])
    wobble = np.radians(cfg.tilt_deg)
    roll = wobble * np.sin(s / 7.0 + cfg.seed)
    pitch_a = wobble * np.sin(s / 11.0 + 2.0 * cfg.seed)
    T = np.tile(np.eye(4), (cfg.scans, 1, 1))
    T[:, :3, :3] = _rot_zyx(yaw, pitch_a, roll)
    T[:, :2, 3] = xy
    T[:, 2, 3] = cfg.sensor_height_m
    return T


def _rot_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``[F, 3, 3]`` rotations Rz(yaw) @ Ry(pitch) @ Rx(roll)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty((len(yaw), 3, 3))
    R[:, 0] = np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], 1)
    R[:, 1] = np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], 1)
    R[:, 2] = np.stack([-sp, cp * sr, cp * cr], 1)
    return R


# --------------------------------------------------------------------------------------
# The LiDAR


class Lidar:
    """A spinning multi-beam LiDAR ray-cast into a :class:`Town`."""

    def __init__(self, town: Town, cfg: SynthConfig) -> None:
        o3d = open3d()

        self.cfg = cfg
        self.scene = o3d.t.geometry.RaycastingScene()
        self.reflectivity: dict[int, float] = {}
        for name, (v, t) in town.meshes.items():
            if len(t) == 0:
                continue
            gid = self.scene.add_triangles(
                o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32))
            )
            self.reflectivity[int(gid)] = MATERIALS[name]
        self.elevation = np.radians(np.linspace(cfg.fov_down_deg, cfg.fov_up_deg, cfg.beams))

    def directions(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Elevation and azimuth (radians) of one scan's rays, azimuth 0 = forward (+x).

        Spinning: ``beams`` rings, rays every ``360 / azimuth_steps`` deg inside the
        horizontal field of view, with a random phase per scan. Rosette: the rays trace a
        7-petal rose over the field of view (an ellipse of ``fov_h_deg`` by the vertical
        spread), turned and phased at random per scan, so successive scans cover
        different lines, as a solid-state sensor's non-repetitive pattern does.
        """
        cfg = self.cfg
        half = math.radians(cfg.fov_h_deg) / 2.0
        if cfg.pattern == "spinning":
            step = 2.0 * np.pi / cfg.azimuth_steps
            n = max(1, int(round(2.0 * half / step)))
            if cfg.fov_h_deg >= 360.0:
                az = (np.arange(n) + rng.random()) * step
            else:
                az = -half + (np.arange(n) + rng.random()) * (2.0 * half / n)
            el, az = np.meshgrid(self.elevation, az, indexing="ij")
            return el, az
        n = cfg.beams * cfg.azimuth_steps
        t = (np.arange(n) + rng.random()) * (2.0 * np.pi / n)
        rho = np.cos(7.0 * t)  # [-1, 1] along the petals
        turn = t + rng.uniform(0.0, 2.0 * np.pi)
        mid = math.radians(cfg.fov_up_deg + cfg.fov_down_deg) / 2.0
        vhalf = math.radians(cfg.fov_up_deg - cfg.fov_down_deg) / 2.0
        return mid + vhalf * rho * np.sin(turn), half * rho * np.cos(turn)

    def scan(self, T_world_sensor: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One scan ``[P, 4]`` float32 (x y z intensity) in the sensor frame."""
        o3d = open3d()

        cfg = self.cfg
        el, az = self.directions(rng)
        dirs = np.stack(
            [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1
        ).reshape(-1, 3)  # [B * A, 3] sensor frame
        R, t = T_world_sensor[:3, :3], T_world_sensor[:3, 3]
        rays = np.empty((len(dirs), 6), dtype=np.float32)  # [N, 6] origin, direction
        rays[:, :3] = t
        rays[:, 3:] = dirs @ R.T
        hit = self.scene.cast_rays(o3d.core.Tensor(rays))
        r = hit["t_hit"].numpy().astype(np.float64)  # [N], inf for a miss
        normals = hit["primitive_normals"].numpy()  # [N, 3] world frame
        gids = hit["geometry_ids"].numpy()
        r = r + rng.normal(0.0, cfg.range_noise_m, size=len(r))
        keep = np.isfinite(r) & (r >= cfg.min_range_m) & (r <= cfg.max_range_m)
        keep &= rng.random(len(r)) >= cfg.dropout
        pts = dirs[keep] * r[keep, None]  # [P, 3]
        cos_inc = np.abs(np.einsum("ij,ij->i", normals[keep], rays[keep, 3:]))
        refl = np.array([self.reflectivity.get(int(g), 0.3) for g in gids[keep]])  # [P]
        inten = refl * (0.3 + 0.7 * cos_inc)
        inten = np.clip(inten + rng.normal(0.0, cfg.intensity_noise, size=len(inten)), 0.0, 1.0)
        out = np.empty((len(pts), 4), dtype=np.float32)
        out[:, :3], out[:, 3] = pts, inten
        return out


# --------------------------------------------------------------------------------------
# The whole sequence


def default_grid(cfg: SynthConfig) -> int:
    """Blocks per side: enough streets for the random walk to spread out."""
    pitch = cfg.block_m + cfg.street_m
    fwd_edges = cfg.scans * cfg.step_m / pitch / 2.0
    return int(max(2, math.ceil(math.sqrt(fwd_edges / 2.0)) + 1))


def generate(
    out: str | os.PathLike,
    cfg: SynthConfig | None = None,
    *,
    overwrite: bool = False,
    progress: bool = False,
) -> dict[str, Any]:
    """Write a synthetic sequence to ``out`` (KITTI layout); returns the summary it stores.

    Raises :class:`InputError` if ``out`` already holds a sequence and not ``overwrite``.
    """
    cfg = cfg or SynthConfig()
    root = Path(out)
    vel = root / "velodyne"
    if vel.exists() and any(vel.iterdir()) and not overwrite:
        raise InputError(
            f"{root}: already holds a sequence (velodyne/); replace it with --overwrite"
        )
    # written aside: a run that fails or is interrupted leaves the previous sequence whole
    with staged(root, ("velodyne", "poses.txt", "times.txt", "synth.json")) as stage:
        info = _generate(stage, cfg, progress)
    log.info("synthetic sequence %s: %s", root, info)
    return info


def _generate(stage: Path, cfg: SynthConfig, progress: bool) -> dict[str, Any]:
    from sgvloc.core.io import write_kitti_bin

    vel = stage / "velodyne"
    vel.mkdir()
    grid = cfg.grid or default_grid(cfg)
    town = build_town(cfg, grid)
    poses = route_poses(cfg, grid, town.pitch)
    lidar = Lidar(town, cfg)
    points = 0
    it = range(cfg.scans)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="synth", unit="scan")
    for i in it:
        scan = lidar.scan(poses[i], np.random.default_rng([cfg.seed, 3, i]))
        if not len(scan):  # a sequence of empty scans is of no use to anyone
            raise InputError(
                f"scan {i} holds no point: nothing within {cfg.min_range_m:g}-"
                f"{cfg.max_range_m:g} m of the sensor (max_range_m too short to reach the "
                "ground and the buildings?)"
            )
        write_kitti_bin(vel / f"{i:06d}.bin", scan)
        points += len(scan)
    with open(stage / "poses.txt", "w") as fh:
        for T in poses:
            fh.write(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n")
    with open(stage / "times.txt", "w") as fh:
        for i in range(cfg.scans):
            fh.write(f"{i / cfg.rate_hz:.6f}\n")
    info = {
        "generator": "sgvloc synth",
        "config": cfg.model_dump(),
        "scans": cfg.scans,
        "blocks": grid * grid,
        "grid": grid,
        "route_m": float(cfg.step_m * (cfg.scans - 1)),
        "primitives": town.stats,
        "mean_points_per_scan": points / cfg.scans,
    }
    (stage / "synth.json").write_text(json.dumps(info, indent=1))
    return info
