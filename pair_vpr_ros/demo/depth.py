"""Depth images of the demo world, aligned with `render.render_view`'s colour pixels.

`render_depth` casts one ray per pixel centre (pixel u, v looks along ((u - cx) / f, (v - cy) / f,
1) in the camera frame of `camera.py`) against the same geometry the colour renderer draws and
keeps the nearest hit, so depth is the camera-frame Z (metres along the optical axis), not the
ray length. Pixels that hit nothing within `max_range` (the sky, the far ground) are 0.

Exact: the ground plane, every front-facing facade (the renderer culls back faces, so one sees
over a low building into the next block, as in the colour image) with the renderer's near plane
and far cut, cars as the renderer's three boxes. Approximated: a person is its billboard (legs,
torso and head at the constant depth of the person's centre, as drawn); pixels on the
anti-aliased edge of a facade get the depth of whichever surface the pixel centre hits, where the
colour is a blend; occluders and facades are z-buffered here but painter-sorted by block distance
in the colour image, which only differs where a car stands right against a facade.
"""

from __future__ import annotations

import math

import numpy as np

from pair_vpr_ros.demo.camera import Camera, to_camera
from pair_vpr_ros.demo.layout import Layout, Occluder

OCCLUDER_RANGE = 90.0  # m; the colour renderer skips cars and people farther than this
MM_PER_M = 1000.0


def render_depth(
    layout: Layout,
    pose: np.ndarray,
    cam: Camera,
    occluders: tuple[Occluder, ...] | list[Occluder] = (),
    max_range: float | None = None,
) -> np.ndarray:
    """Depth seen from `pose` (x, y, yaw) -> [H, W] float32 metres along the optical axis (Z);
    0 where nothing lies within `max_range` (default: the camera's far plane, 260 m)."""
    max_range = cam.far if max_range is None else float(max_range)
    xn = (np.arange(cam.width) - cam.cx) / cam.f  # [W] ray slope right
    yn = (np.arange(cam.height) - cam.cy) / cam.f  # [H] ray slope down
    depth = np.full((cam.height, cam.width), np.inf)
    with np.errstate(divide="ignore"):
        ground = np.where(yn > 0, cam.height_m / yn, np.inf)  # Z where the ray meets z = 0
    depth[:] = ground[:, None]
    _facades(depth, layout, pose, cam, xn, yn)
    for occ in occluders:
        if math.hypot(occ.x - pose[0], occ.y - pose[1]) >= OCCLUDER_RANGE:
            continue
        if occ.kind == "car":
            _car(depth, occ, pose, cam, xn, yn)
        else:
            _person(depth, occ, pose, cam)
    depth[(depth < cam.near) | (depth > max_range)] = 0.0
    return depth.astype(np.float32)


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """float metres [H, W] -> uint16 millimetres (16UC1); 0 where invalid or beyond 65.535 m."""
    mm = np.nan_to_num(np.asarray(depth, np.float64), nan=0.0) * MM_PER_M
    return np.where((mm > 0) & (mm <= 65535), np.round(mm), 0).astype(np.uint16)


def _ray_dirs(pose: np.ndarray, xn: np.ndarray) -> np.ndarray:
    """Horizontal world direction [W, 2] of each column's rays, scaled so Z grows by 1 per unit."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    return np.stack([xn * s + c, -xn * c + s], axis=1)  # x_cam axis (s, -c), z_cam axis (c, s)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _facades(
    depth: np.ndarray,
    layout: Layout,
    pose: np.ndarray,
    cam: Camera,
    xn: np.ndarray,
    yn: np.ndarray,
) -> None:
    """Nearest front-facing facade per pixel into `depth` [H, W] (Z-buffer, in place)."""
    if "depth_facades" not in layout.cache:
        p0 = np.array([f.p0 for f in layout.facades], np.float64)
        p1 = np.array([f.p1 for f in layout.facades], np.float64)
        heights = np.array([f.height for f in layout.facades], np.float64)
        layout.cache["depth_facades"] = (p0, p1, heights)
    p0, p1, heights = layout.cache["depth_facades"]
    origin = np.asarray(pose[:2], np.float64)
    edge = p1 - p0
    facing = _cross(edge, origin - p0) < 0  # normal (e_y, -e_x) points at the camera
    pc0, pc1 = to_camera(p0, pose, cam), to_camera(p1, pose, cam)
    near = np.minimum(np.hypot(pc0[:, 0], pc0[:, 2]), np.hypot(pc1[:, 0], pc1[:, 2])) < cam.far
    keep = np.flatnonzero(facing & near)
    if not len(keep):
        return
    p0, edge, heights = p0[keep], edge[keep], heights[keep]
    rays = _ray_dirs(pose, xn)  # [W, 2]
    denom = _cross(rays[:, None, :], edge[None])  # [W, F]
    rel = p0 - origin  # [F, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = _cross(rel[None], edge[None]) / denom  # Z along each column's rays
        u = _cross(rel[None], rays[:, None, :]) / denom  # position along the facade
    t = np.where((u >= 0) & (u <= 1) & (t >= cam.near) & np.isfinite(t), t, np.inf)
    # Only the K facades a column crosses matter: keep those, nearest first.
    k = max(1, int(np.isfinite(t).sum(axis=1).max()))
    order = np.argsort(t, axis=1)[:, :k]  # [W, K]
    t = np.take_along_axis(t, order, axis=1)
    top = heights[order]  # [W, K]
    # Per pixel: the ray at depth t is at height h - yn * t; it hits when that is in [0, top].
    height_at = cam.height_m - yn[:, None, None] * t[None]  # [H, W, K]
    hit = (height_at >= 0) & (height_at <= top[None])
    z = np.where(hit, t[None], np.inf).min(axis=2)
    np.minimum(depth, z, out=depth)


def _car(
    depth: np.ndarray, occ: Occluder, pose: np.ndarray, cam: Camera, xn: np.ndarray, yn: np.ndarray
) -> None:
    """The three boxes of `occluders._draw_car` (tyres, body, glass cabin) by ray casting."""
    length, width, height = occ.size
    fwd = np.array([math.cos(occ.yaw), math.sin(occ.yaw)])
    centre = np.array([occ.x, occ.y])
    boxes = [
        (centre, length - 0.5, width - 0.1, 0.0, 0.4),
        (centre, length, width, 0.3, 0.62 * height),
        (centre - fwd * 0.1 * length, 0.55 * length, width - 0.2, 0.62 * height, height),
    ]
    rays = _ray_dirs(pose, xn)  # [W, 2]
    origin = np.asarray(pose[:2], np.float64)
    left = np.array([-fwd[1], fwd[0]])
    for mid, ln, wd, z0, z1 in boxes:
        rel = origin - mid
        # Slabs along the car's length, width and height; ray parameter = camera Z.
        o = [rel @ fwd, rel @ left]
        d = [rays @ fwd, rays @ left]  # [W] each
        lo = np.full((1, cam.width), cam.near)
        hi = np.full((1, cam.width), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for oi, di, half in ((o[0], d[0], ln / 2), (o[1], d[1], wd / 2)):
                ta, tb = (-half - oi) / di, (half - oi) / di
                inside = np.abs(oi) <= half
                ta = np.where(di == 0, np.where(inside, -np.inf, np.inf), ta)
                tb = np.where(di == 0, np.where(inside, np.inf, -np.inf), tb)
                lo = np.maximum(lo, np.minimum(ta, tb)[None])
                hi = np.minimum(hi, np.maximum(ta, tb)[None])
            dz = -yn[:, None]  # world height change per unit Z
            oz = cam.height_m
            ta, tb = (z0 - oz) / dz, (z1 - oz) / dz
            flat = dz == 0
            inside = z0 <= oz <= z1
            ta = np.where(flat, -np.inf if inside else np.inf, ta)
            tb = np.where(flat, np.inf if inside else -np.inf, tb)
            lo = np.maximum(lo, np.minimum(ta, tb))
            hi = np.minimum(hi, np.maximum(ta, tb))
        np.minimum(depth, np.where(lo <= hi, lo, np.inf), out=depth)


def _person(depth: np.ndarray, occ: Occluder, pose: np.ndarray, cam: Camera) -> None:
    """Legs, torso and head as drawn by `occluders._draw_person`, at the centre's depth."""
    centre = to_camera(np.array([[occ.x, occ.y, 0.0]]), pose, cam)[0]
    z = float(centre[2])
    if z < cam.near + 0.5:
        return
    s = cam.f / z
    u0 = cam.cx + s * centre[0]
    ground_v = cam.cy + s * cam.height_m
    h = occ.size[2]
    uu = np.arange(cam.width)[None, :]
    vv = np.arange(cam.height)[:, None]
    legs = (np.abs(uu - u0) <= 0.17 * s) & (vv >= ground_v - 0.47 * h * s) & (vv <= ground_v)
    torso = (np.abs(uu - u0) <= 0.25 * s) & (vv >= ground_v - 0.86 * h * s)
    torso &= vv <= ground_v - 0.47 * h * s
    head = (uu - u0) ** 2 + (vv - (ground_v - (h - 0.12) * s)) ** 2 <= (0.12 * s) ** 2
    np.minimum(depth, np.where(legs | torso | head, z, np.inf), out=depth)
