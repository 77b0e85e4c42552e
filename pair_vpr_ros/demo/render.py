"""Render a view of the demo world with numpy and OpenCV only.

Sky and ground are gradients with per-row fog; sidewalks and lane dashes are ground polygons.
Each visible facade is clipped to the view frustum in its own length parameter, cut into chunks of
similar depth and warped from a mip level of its texture with a homography. Blocks and occluders
are drawn far to near (painter's order), which suits a camera in the streets of a grid of convex
blocks.
"""

from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np

from pair_vpr_ros.demo.camera import Camera, fill_polygon, project, to_camera
from pair_vpr_ros.demo.facades import PX_PER_M, facade_texture
from pair_vpr_ros.demo.layout import SIDEWALK_WIDTH, STREET_HALF_WIDTH, Layout, Lighting, Occluder
from pair_vpr_ros.demo.occluders import draw_occluder
from pair_vpr_ros.demo.world import World

NOISE_SIGMA = 2.0  # grey levels of per-pixel sensor noise
NOISE_BANK_PAD = 64  # px; frames take noise windows at random offsets up to this
SIDEWALK_RANGE = 150.0  # m; farther sidewalks are thinner than a pixel row
OCCLUDER_RANGE = 90.0  # m; farther cars and people are a few pixels and are skipped
MAX_DEPTH_RATIO = 1.6  # far / near depth within one facade chunk (one mip level per chunk)
_RAMP = np.arange(256, dtype=np.float32)[:, None]  # [256, 1] grey levels for tone curves


def render_frame(world: World, i: int, size: tuple[int, int] | None = None) -> np.ndarray:
    """Frame `i` of the drive -> [H, W, 3] uint8 RGB; `size` (W, H) overrides the world's size."""
    if not 0 <= i < world.num_frames:
        raise IndexError(f"frame {i} out of range 0..{world.num_frames - 1}")
    w, h = size or (world.config.width, world.config.height)
    cam = Camera(width=w, height=h)
    lighting, occluders = world.lighting_of(i), world.occluders_of(i)
    return render_view(world.layout, world.poses[i], lighting, occluders, cam, (world.seed, i))


def render_view(
    layout: Layout,
    pose: np.ndarray,
    lighting: Lighting,
    occluders: tuple[Occluder, ...] | list[Occluder],
    cam: Camera,
    noise_seed: tuple[int, ...] | None = None,
) -> np.ndarray:
    """View from `pose` (x, y, yaw) -> [H, W, 3] uint8 RGB; deterministic per noise seed."""
    arrays = _arrays(layout)
    img = _background(arrays, pose, lighting, cam)
    cam_xy = np.asarray(pose[:2], np.float64)
    lo, hi, pc0, pc1 = _facade_intervals(arrays, pose, cam)
    visible = np.flatnonzero(lo < hi)
    by_block: dict[int, list[int]] = {}
    for f in visible.tolist():
        by_block.setdefault(int(arrays["block"][f]), []).append(f)
    blocks = arrays["blocks"][list(by_block)]
    gap = np.maximum(np.maximum(blocks[:, :2] - cam_xy, cam_xy - blocks[:, 2:]), 0.0)
    items = list(zip(np.hypot(gap[:, 0], gap[:, 1]).tolist(), by_block.values(), strict=True))
    for o in occluders:
        d = math.hypot(o.x - cam_xy[0], o.y - cam_xy[1])
        if d < OCCLUDER_RANGE:
            items.append((d, o))
    sun = np.asarray(lighting.sun) / np.hypot(*lighting.sun)
    shade = (0.8 + 0.2 * (arrays["normal"] @ sun)).tolist()
    for _, item in sorted(items, key=lambda t: -t[0]):
        if isinstance(item, Occluder):
            draw_occluder(img, item, pose, cam, lighting)
            continue
        for f in item:
            _draw_facade(img, layout, f, lo[f], hi[f], pc0[f], pc1[f], shade[f], lighting, cam)
    out = cv2.LUT(img, _lut(lighting))
    if noise_seed is not None:
        pos, neg = _noise_bank(cam.width, cam.height)
        dy, dx = np.random.default_rng(noise_seed).integers(0, NOISE_BANK_PAD, 2)
        window = (slice(dy, dy + cam.height), slice(dx, dx + cam.width))
        out = cv2.subtract(cv2.add(out, pos[window]), neg[window])
    return out


@lru_cache(maxsize=4)
def _noise_bank(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Fixed Gaussian sensor noise [H+pad, W+pad, 3] split into positive and negative uint8 parts;
    frames take shifted windows of it (much cheaper than fresh noise per frame)."""
    shape = (height + NOISE_BANK_PAD, width + NOISE_BANK_PAD, 3)
    noise = np.random.default_rng(0).standard_normal(shape) * NOISE_SIGMA
    noise = np.round(noise)
    return np.clip(noise, 0, 255).astype(np.uint8), np.clip(-noise, 0, 255).astype(np.uint8)


def _arrays(layout: Layout) -> dict:
    """Per-layout numpy views of the facades and lane dashes, computed once and cached."""
    if "arrays" not in layout.cache:
        p0 = np.array([f.p0 for f in layout.facades])
        p1 = np.array([f.p1 for f in layout.facades])
        d = (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
        layout.cache["arrays"] = {
            "p0": p0,
            "p1": p1,
            "normal": np.stack([d[:, 1], -d[:, 0]], axis=1),
            "blocks": layout.blocks,
            "block": np.array([f.block for f in layout.facades]),
            "dashes": _lane_dashes(layout),
            "sidewalks": _sidewalks(layout.blocks),
        }
        layout.cache["textures"] = {}
    return layout.cache["arrays"]


def _sidewalks(blocks: np.ndarray) -> np.ndarray:
    """Blocks [B, 4] grown by the sidewalk -> ground quads [B, 4, 2]."""
    x0, y0 = blocks[:, 0] - SIDEWALK_WIDTH, blocks[:, 1] - SIDEWALK_WIDTH
    x1, y1 = blocks[:, 2] + SIDEWALK_WIDTH, blocks[:, 3] + SIDEWALK_WIDTH
    return np.stack([np.c_[x0, y0], np.c_[x1, y0], np.c_[x1, y1], np.c_[x0, y1]], axis=1)


def _lane_dashes(layout: Layout, dash: float = 3.0, period: float = 9.0) -> np.ndarray:
    """Centre-line dashes of every street, skipping intersections -> [D, 4, 2] ground corners."""
    quads = []
    for lines, across, axis in ((layout.xs, layout.ys, 1), (layout.ys, layout.xs, 0)):
        for c in lines:
            for a, b in zip(across[:-1], across[1:], strict=True):
                for s in np.arange(
                    a + STREET_HALF_WIDTH + 1.0, b - STREET_HALF_WIDTH - dash, period
                ):
                    q = np.array(
                        [(c - 0.08, s), (c + 0.08, s), (c + 0.08, s + dash), (c - 0.08, s + dash)]
                    )
                    quads.append(q if axis == 1 else q[:, ::-1])
    return np.array(quads).reshape(-1, 4, 2)


def _background(arrays: dict, pose: np.ndarray, lighting: Lighting, cam: Camera) -> np.ndarray:
    """Sky gradient above the horizon; road, sidewalks and dashes with per-row fog below."""
    img = _sky(lighting, cam).copy()  # uint8
    r0 = int(math.floor(cam.cy)) + 1
    labels = np.zeros((cam.height - r0, cam.width), np.uint8)
    quads = to_camera(arrays["sidewalks"], pose, cam)  # [B, 4, 3]
    near = np.hypot(quads[..., 0], quads[..., 2]).min(axis=1) < SIDEWALK_RANGE
    for quad in quads[near & (quads[..., 2].max(axis=1) > cam.near)]:
        fill_polygon(labels, quad, 1, cam, r0)
    dashes = to_camera(arrays["dashes"], pose, cam)
    z = dashes[..., 2]
    keep = (z.min(axis=1) > cam.near) & (z.max(axis=1) < 80.0)
    keep &= (np.abs(dashes[..., 0]) < cam.tan_half * z + 1.0).any(axis=1)
    if keep.any():
        px = project(dashes[keep], cam) - (0.0, r0)
        cv2.fillPoly(labels, list(np.round(px * 16).astype(np.int32)), 2, cv2.LINE_8, 4)
    rows = np.arange(r0, cam.height, dtype=np.float32)
    fog = (1.0 - np.exp(-cam.f * cam.height_m / (rows - cam.cy) / lighting.fog_distance))[:, None]
    colours = np.array([lighting.road, lighting.sidewalk, (225, 225, 215)], np.float32)
    fog_colour = np.asarray(lighting.fog_colour, np.float32)
    ground = colours[labels] * (1.0 - fog[..., None]) + fog_colour * fog[..., None]
    img[r0:] = cv2.convertScaleAbs(ground)
    return img


@lru_cache(maxsize=16)
def _sky(lighting: Lighting, cam: Camera) -> np.ndarray:
    """[H, W, 3] uint8 sky gradient (the ground rows are overwritten per frame)."""
    rows = np.arange(cam.height, dtype=np.float32)
    t = np.clip((cam.cy - rows) / max(cam.cy, 1.0), 0.0, 1.0)[:, None] ** 0.6
    top = np.asarray(lighting.sky_top, np.float32)
    hor = np.asarray(lighting.sky_horizon, np.float32)
    col = np.round(hor + (top - hor) * t)
    return np.repeat(col[:, None, :], cam.width, axis=1).astype(np.uint8)


@lru_cache(maxsize=16)
def _lut(lighting: Lighting) -> np.ndarray:
    """Per-channel tone curve [1, 256, 3] uint8: contrast around mid grey, gamma, gain and tint."""
    x = np.arange(256, dtype=np.float64) / 255.0
    y = np.clip((x - 0.5) * lighting.contrast + 0.5, 0.0, 1.0) ** lighting.gamma * lighting.gain
    curves = [np.clip(y * t, 0.0, 1.0) for t in lighting.tint]
    return np.round(np.stack(curves, axis=-1) * 255).astype(np.uint8)[None]


def _facade_intervals(arrays: dict, pose: np.ndarray, cam: Camera) -> tuple[np.ndarray, ...]:
    """Visible part [lo, hi] of each facade's length parameter (lo >= hi: hidden), endpoints in the
    camera frame [F, 3]. Backfaces, the near plane and the horizontal frustum are cut exactly."""
    pc0, pc1 = to_camera(arrays["p0"], pose, cam), to_camera(arrays["p1"], pose, cam)
    x0, z0, dx, dz = pc0[:, 0], pc0[:, 2], pc1[:, 0] - pc0[:, 0], pc1[:, 2] - pc0[:, 2]
    lo, hi = np.zeros(len(x0)), np.ones(len(x0))
    tn = cam.tan_half
    for a, b in ((z0 - cam.near, dz), (tn * z0 - x0, tn * dz - dx), (tn * z0 + x0, tn * dz + dx)):
        # Each constraint a + b t >= 0 bounds t from one side.
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -a / b
        lo = np.where(b > 1e-12, np.maximum(lo, t), lo)
        hi = np.where(b < -1e-12, np.minimum(hi, t), hi)
        hi = np.where((np.abs(b) <= 1e-12) & (a < 0), -1.0, hi)
    facing = np.einsum("fi,fi->f", np.asarray(pose[:2]) - arrays["p0"], arrays["normal"]) > 0
    near = np.minimum(np.hypot(x0, z0), np.hypot(pc1[:, 0], pc1[:, 2])) < cam.far
    hi = np.where(facing & near, hi, -1.0)
    return lo, hi, pc0, pc1


def _pyramid(layout: Layout, fid: int) -> list[np.ndarray]:
    """Mip levels of a facade texture, RGBA with a 1 px transparent frame of edge colours: warped
    with BORDER_REPLICATE they give unpremultiplied colour and an anti-aliased alpha edge."""
    cache = layout.cache["textures"]
    if fid not in cache:
        levels = [facade_texture(layout.seed, layout.facades[fid])]
        while min(levels[-1].shape[:2]) >= 16:
            levels.append(cv2.pyrDown(levels[-1]))
        framed = []
        for rgb in levels:
            rgba = cv2.copyMakeBorder(
                cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA), 1, 1, 1, 1, cv2.BORDER_REPLICATE
            )
            rgba[[0, -1], :, 3] = 0
            rgba[:, [0, -1], 3] = 0
            framed.append(rgba)
        cache[fid] = framed
    return cache[fid]


def _chunks(lo: float, hi: float, za: float, zb: float) -> np.ndarray:
    """Split [lo, hi] where depth goes za -> zb linearly into pieces of depth ratio <= 1.6."""
    ratio = max(za, zb) / min(za, zb)
    n = min(8, max(1, math.ceil(math.log(ratio) / math.log(MAX_DEPTH_RATIO))))
    if n == 1:
        return np.array([lo, hi])
    z = za * (zb / za) ** np.linspace(0.0, 1.0, n + 1)  # geometric in depth
    return lo + (hi - lo) * (z - za) / (zb - za)


def _draw_facade(
    img: np.ndarray,
    layout: Layout,
    fid: int,
    lo: float,
    hi: float,
    pc0: np.ndarray,
    pc1: np.ndarray,
    shade: float,
    lighting: Lighting,
    cam: Camera,
) -> None:
    """Warp the visible part [lo, hi] of facade `fid` into `img` [H, W, 3] uint8, shaded and fogged
    by a per-chunk tone curve and blended by the warped alpha."""
    pyr = _pyramid(layout, fid)
    x0, z0 = float(pc0[0]), float(pc0[2])
    dx, dz = float(pc1[0]) - x0, float(pc1[2]) - z0
    f, cx, cy, cam_h = cam.f, cam.cx, cam.cy, cam.height_m
    y_top = cam_h - layout.facades[fid].height
    fog_colour = np.float32([*lighting.fog_colour, 0.0])  # alpha passes through the tone curve
    ts = _chunks(lo, hi, z0 + dz * lo, z0 + dz * hi)
    for ta, tb in zip(ts[:-1].tolist(), ts[1:].tolist(), strict=True):
        za, zb = z0 + dz * ta, z0 + dz * tb
        xa, xb = cx + f * (x0 + dx * ta) / za, cx + f * (x0 + dx * tb) / zb
        if abs(xb - xa) < 0.3:
            continue
        top_a, top_b = cy + f * y_top / za, cy + f * y_top / zb
        bot_a, bot_b = cy + f * cam_h / za, cy + f * cam_h / zb
        z_mid = 0.5 * (za + zb)
        # One mip level per chunk from the geometric mean of vertical and horizontal minification.
        minify = math.sqrt(PX_PER_M * z_mid / f * (tb - ta) * pyr[0].shape[1] / abs(xb - xa))
        level = min(len(pyr) - 1, max(0, math.floor(math.log2(max(1.0, minify)))))
        tex = pyr[level]
        th, tw = tex.shape[0] - 2, tex.shape[1] - 2  # inside the transparent frame
        ua, ub = ta * tw + 0.5, tb * tw + 0.5
        c0, c1 = max(0, int(ua) - 2), min(tw + 2, math.ceil(ub) + 3)
        bx0, bx1 = max(0, math.floor(min(xa, xb))), min(cam.width, math.ceil(max(xa, xb)) + 1)
        by0 = max(0, math.floor(min(top_a, top_b)))
        by1 = min(cam.height, math.ceil(max(bot_a, bot_b)) + 1)
        if bx1 <= bx0 or by1 <= by0 or c1 - c0 < 2:
            continue
        src = np.float32(
            [(ua - c0, 0.5), (ub - c0, 0.5), (ub - c0, th + 0.5), (ua - c0, th + 0.5)]
        )
        dst = np.float32([(xa, top_a), (xb, top_b), (xb, bot_b), (xa, bot_a)])
        dst -= np.float32([bx0, by0])
        warped = cv2.warpPerspective(
            tex[:, c0:c1],
            cv2.getPerspectiveTransform(src, dst),
            (bx1 - bx0, by1 - by0),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        fog = 1.0 - math.exp(-z_mid / lighting.fog_distance)
        lut = _RAMP * np.float32([*(shade * (1.0 - fog),) * 3, 1.0]) + fog * fog_colour
        warped = cv2.LUT(warped, np.clip(lut, 0, 255).astype(np.uint8)[None])
        alpha = warped[..., 3].astype(np.float32) * (1.0 / 255.0)
        roi = img[by0:by1, bx0:bx1]
        roi[:] = cv2.blendLinear(cv2.cvtColor(warped, cv2.COLOR_RGBA2RGB), roi, alpha, 1.0 - alpha)
