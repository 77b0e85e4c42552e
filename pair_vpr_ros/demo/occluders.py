"""Draw the occluders of a visit: cars as flat-shaded boxes, people as camera-facing billboards."""

from __future__ import annotations

import math
from collections.abc import Callable

import cv2
import numpy as np

from pair_vpr_ros.demo.camera import SHIFT, Camera, fill_polygon, project, to_camera
from pair_vpr_ros.demo.layout import Lighting, Occluder

TYRE = (28, 28, 30)
GLASS = (55, 70, 90)
SKIN = (205, 160, 130)
TROUSERS = (45, 45, 60)


def draw_occluder(
    img: np.ndarray, occ: Occluder, pose: np.ndarray, cam: Camera, lighting: Lighting
) -> None:
    """Draw `occ` into `img` [H, W, 3] uint8 as seen from `pose` (x, y, yaw)."""
    centre = to_camera(np.array([[occ.x, occ.y, 0.0]]), pose, cam)[0]
    if centre[2] < -occ.size[0] or abs(centre[0]) > cam.tan_half * max(centre[2], 0) + occ.size[0]:
        return  # behind the camera or well outside the view
    fog = 1.0 - math.exp(-max(centre[2], 0.0) / lighting.fog_distance)

    def tone(colour: tuple[int, ...], shade: float = 1.0) -> tuple[float, ...]:
        return tuple(
            min(c * shade, 255.0) * (1.0 - fog) + f * fog
            for c, f in zip(colour, lighting.fog_colour, strict=True)
        )

    if occ.kind == "car":
        _draw_car(img, occ, pose, cam, lighting, tone)
    else:
        _draw_person(img, occ, centre, cam, tone)


def _draw_car(
    img: np.ndarray,
    occ: Occluder,
    pose: np.ndarray,
    cam: Camera,
    lighting: Lighting,
    tone: Callable[..., tuple[float, ...]],
) -> None:
    """Tyre band, body and glass cabin as three boxes; only faces turned to the camera."""
    length, width, height = occ.size
    fwd = np.array([math.cos(occ.yaw), math.sin(occ.yaw)])
    left = np.array([-fwd[1], fwd[0]])
    sun = np.asarray(lighting.sun) / np.hypot(*lighting.sun)
    centre = np.array([occ.x, occ.y])
    parts = [
        (centre, length - 0.5, width - 0.1, 0.0, 0.4, TYRE),
        (centre, length, width, 0.3, 0.62 * height, occ.colour),
        (centre - fwd * 0.1 * length, 0.55 * length, width - 0.2, 0.62 * height, height, GLASS),
    ]
    signs = np.array([(1, 1), (-1, 1), (-1, -1), (1, -1)], np.float64)
    rings = [mid + signs @ np.stack([fwd * ln / 2, left * wd / 2]) for mid, ln, wd, *_ in parts]
    corners = np.concatenate(
        [
            np.c_[ring, np.full(4, z)]
            for ring, part in zip(rings, parts, strict=True)
            for z in part[3:5]
        ]
    )  # [24, 3]: per part the bottom ring, then the top ring
    pc = to_camera(corners, pose, cam)
    px = None
    if pc[:, 2].min() >= cam.near:
        px = np.round(project(pc, cam) * (1 << SHIFT)).astype(np.int32)
    cam_xy = np.asarray(pose[:2], np.float64)
    for p, (ring, (mid, _, _, _, z1, colour)) in enumerate(zip(rings, parts, strict=True)):
        base = 8 * p
        normals = (ring + np.roll(ring, -1, axis=0)) / 2 - mid  # [4, 2] outward, side k: k -> k+1
        facing = np.einsum("ki,ki->k", cam_xy - ring, normals) > 0
        light = normals @ sun / np.hypot(normals[:, 0], normals[:, 1])
        faces = [
            ([base + k, base + (k + 1) % 4, base + 4 + (k + 1) % 4, base + 4 + k], 0.75 + 0.2 * lk)
            for k, lk in enumerate(light.tolist())
            if facing[k]
        ]
        if cam.height_m > z1:
            faces.append(([base + 4, base + 5, base + 6, base + 7], 1.1))
        for idx, shade in faces:
            if px is None:  # part of the car is behind the near plane: clip each face
                fill_polygon(img, pc[idx], tone(colour, shade), cam)
            else:
                cv2.fillPoly(img, [px[idx]], tone(colour, shade), cv2.LINE_8, SHIFT)


def _draw_person(
    img: np.ndarray,
    occ: Occluder,
    centre: np.ndarray,
    cam: Camera,
    tone: Callable[..., tuple[float, ...]],
) -> None:
    """Legs, torso and head as rectangles and a circle scaled by depth."""
    if centre[2] < cam.near + 0.5:
        return
    s = cam.f / centre[2]
    u = cam.cx + s * centre[0]
    ground_v = cam.cy + s * cam.height_m
    height = occ.size[2]

    def rect(half_w: float, z0: float, z1: float, colour: tuple[float, ...]) -> None:
        p = (u - half_w * s, ground_v - z1 * s)
        q = (u + half_w * s, ground_v - z0 * s)
        pts = np.array([p, (q[0], p[1]), q, (p[0], q[1])]) * (1 << SHIFT)
        cv2.fillPoly(img, [np.round(pts).astype(np.int32)], colour, cv2.LINE_8, SHIFT)

    rect(0.17, 0.0, 0.47 * height, tone(TROUSERS))
    rect(0.25, 0.47 * height, 0.86 * height, tone(occ.colour))
    head = np.round(np.array([u, ground_v - (height - 0.12) * s]) * (1 << SHIFT)).astype(int)
    radius = int(round(0.12 * s * (1 << SHIFT)))
    cv2.circle(img, tuple(int(v) for v in head), max(radius, 1), tone(SKIN), -1, cv2.LINE_8, SHIFT)
