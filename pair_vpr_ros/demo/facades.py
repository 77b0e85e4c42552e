"""Procedural facade textures: distinctive per building, deterministic per (layout seed, facade).

Big, low-frequency features (wall colour, sign band, mural, cornice, window rhythm) carry the
identity of a building, so places stay recognisable at 112-126 px.
"""

from __future__ import annotations

import cv2
import numpy as np

from pair_vpr_ros.demo.layout import Facade

PX_PER_M = 12.0  # texture resolution at mip level 0


def _hsv(rng: np.random.Generator, s: tuple[int, int], v: tuple[int, int]) -> tuple[int, ...]:
    """Random RGB colour with OpenCV HSV saturation range `s` and value range `v`."""
    hsv = np.array([[[rng.integers(0, 180), rng.integers(*s), rng.integers(*v)]]], np.uint8)
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0])


def facade_texture(layout_seed: int, facade: Facade, ppm: float = PX_PER_M) -> np.ndarray:
    """Facade image [H, W, 3] uint8 RGB; row 0 is the roof line, column 0 the left end."""
    rng = np.random.default_rng([layout_seed, facade.id, 7])
    w, h = max(8, round(facade.length * ppm)), max(8, round(facade.height * ppm))
    img = np.empty((h, w, 3), np.uint8)
    img[:] = _hsv(rng, (25, 190), (80, 235))
    noise = rng.normal(0.0, 7.0, (max(2, h // 24), max(2, w // 24), 1)).astype(np.float32)
    noise = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)[..., None]
    img[:] = np.clip(img + noise, 0, 255).astype(np.uint8)
    accent = _hsv(rng, (150, 256), (120, 256))
    ground = int(rng.uniform(3.6, 4.6) * ppm)
    _wall_pattern(img, rng, ppm, ground)
    _windows(img, rng, ppm, ground)
    _shopfront(img, rng, ppm, ground, accent)
    if rng.random() < 0.65:
        _feature(img, rng, ppm, ground, accent)
    cornice = int(rng.uniform(0.5, 1.3) * ppm)
    cv2.rectangle(img, (0, 0), (w - 1, cornice), _hsv(rng, (0, 256), (30, 240)), -1)
    return img


def _wall_pattern(img: np.ndarray, rng: np.random.Generator, ppm: float, ground: int) -> None:
    """Floor slabs or pilasters in a shade of the wall colour."""
    h, w = img.shape[:2]
    shade = tuple(int(c) for c in np.clip(img[h // 2, w // 2] * rng.uniform(0.6, 1.3), 0, 255))
    style = int(rng.integers(3))
    if style == 1:
        step = int(rng.uniform(3.0, 4.0) * ppm)
        for y in range(h - ground, 0, -step):
            cv2.rectangle(img, (0, y - int(0.35 * ppm)), (w - 1, y), shade, -1)
    elif style == 2:
        step = int(rng.uniform(2.5, 5.0) * ppm)
        for x in range(0, w, step):
            cv2.rectangle(img, (x, 0), (x + int(0.5 * ppm), h - ground), shade, -1)


def _windows(img: np.ndarray, rng: np.random.Generator, ppm: float, ground: int) -> None:
    """A grid of windows on the upper floors: single, ribbon or curtain-wall glass."""
    h, w = img.shape[:2]
    glass = _hsv(rng, (20, 160), (35, 120))
    frame = (235, 235, 230) if rng.random() < 0.5 else _hsv(rng, (0, 120), (20, 200))
    floor = rng.uniform(3.0, 4.0) * ppm
    style = int(rng.integers(4))
    if style == 3:  # curtain wall with mullions
        top = int(rng.uniform(1.0, 2.0) * ppm)
        cv2.rectangle(img, (int(0.3 * ppm), top), (w - int(0.3 * ppm), h - ground), glass, -1)
        for x in np.arange(0, w, rng.uniform(1.2, 2.5) * ppm):
            cv2.line(img, (int(x), top), (int(x), h - ground), frame, max(1, int(0.12 * ppm)))
        for y in np.arange(h - ground, top, -floor):
            cv2.line(img, (0, int(y)), (w - 1, int(y)), frame, max(1, int(0.2 * ppm)))
        return
    win_w, win_h = rng.uniform(0.8, 2.0) * ppm, rng.uniform(1.2, 2.0) * ppm
    bay = win_w + rng.uniform(0.6, 2.2) * ppm
    n = max(1, int((w - 0.6 * ppm) // bay))
    x0 = (w - n * bay) / 2 + (bay - win_w) / 2
    border = max(1, int(0.1 * ppm))
    for y in np.arange(h - ground - floor + (floor - win_h) / 2, 1.5 * ppm, -floor):
        if style == 1:  # ribbon window along the whole floor
            p, q = (int(x0), int(y)), (int(x0 + (n - 1) * bay + win_w), int(y + win_h * 0.7))
            cv2.rectangle(img, p, q, glass, -1)
            cv2.rectangle(img, p, q, frame, border)
            continue
        for k in range(n):
            p = (int(x0 + k * bay), int(y))
            q = (int(x0 + k * bay + win_w), int(y + win_h))
            cv2.rectangle(img, p, q, glass, -1)
            cv2.rectangle(img, p, q, frame, border)
            if style == 2:  # arched top
                cv2.ellipse(
                    img,
                    ((p[0] + q[0]) // 2, p[1]),
                    (int(win_w / 2), int(win_w / 3)),
                    0,
                    180,
                    360,
                    glass,
                    -1,
                )


def _shopfront(
    img: np.ndarray, rng: np.random.Generator, ppm: float, ground: int, accent: tuple[int, ...]
) -> None:
    """Ground floor: shop windows, doors and a coloured sign band with block 'lettering'."""
    h, w = img.shape[:2]
    glass = _hsv(rng, (10, 120), (30, 90))
    cv2.rectangle(
        img, (int(0.4 * ppm), h - int(2.8 * ppm)), (w - int(0.4 * ppm), h - 1), glass, -1
    )
    for _ in range(int(rng.integers(1, 3))):
        x = int(rng.uniform(0.5, max(0.6, w / ppm - 2.0)) * ppm)
        door = _hsv(rng, (0, 200), (20, 160))
        cv2.rectangle(img, (x, h - int(2.4 * ppm)), (x + int(1.3 * ppm), h - 1), door, -1)
    sign_top = h - ground + int(0.2 * ppm)
    sign_bot = h - int(2.9 * ppm)
    if sign_bot - sign_top < 4:
        return
    span = (int(rng.uniform(0.0, 0.3) * w), int(rng.uniform(0.7, 1.0) * w))
    cv2.rectangle(img, (span[0], sign_top), (span[1], sign_bot), accent, -1)
    ink = (20, 20, 20) if sum(accent) > 380 else (245, 245, 245)
    x, letter = span[0] + int(0.4 * ppm), int(0.55 * ppm)
    while x + letter < span[1] - int(0.3 * ppm):
        if rng.random() < 0.85:
            cv2.rectangle(img, (x, sign_top + 3), (x + letter - 3, sign_bot - 3), ink, -1)
        x += letter + int(rng.integers(0, 3))


def _feature(
    img: np.ndarray, rng: np.random.Generator, ppm: float, ground: int, accent: tuple[int, ...]
) -> None:
    """One large mural, banner or stripe panel on the upper floors."""
    h, w = img.shape[:2]
    colour = _hsv(rng, (170, 256), (140, 256))
    top, bot = int(1.5 * ppm), h - ground - int(0.5 * ppm)
    if bot - top < 2 * ppm:
        return
    size = int(min(rng.uniform(3.0, 7.0) * ppm, (bot - top) * 0.9, w * 0.8))
    cx = int(rng.uniform(0.3, 0.7) * w)
    cy = int(rng.uniform(top + size / 2, max(top + size / 2 + 1, bot - size / 2)))
    kind = int(rng.integers(5))
    if kind == 0:
        cv2.circle(img, (cx, cy), size // 2, colour, -1)
        cv2.circle(img, (cx, cy), size // 4, accent, -1)
    elif kind == 1:
        r = size // 2
        pts = np.array([(cx, cy - r), (cx + r, cy), (cx, cy + r), (cx - r, cy)], np.int32)
        cv2.fillPoly(img, [pts], colour)
    elif kind == 2:
        r = size // 2
        cv2.fillPoly(
            img, [np.array([(cx, cy - r), (cx + r, cy + r), (cx - r, cy + r)], np.int32)], colour
        )
    elif kind == 3:  # vertical banner
        bw = int(rng.uniform(1.0, 2.0) * ppm)
        cv2.rectangle(img, (cx - bw // 2, top), (cx + bw // 2, bot), colour, -1)
        cv2.rectangle(img, (cx - bw // 2, top), (cx + bw // 2, top + bw), accent, -1)
    else:  # striped panel
        stripe = max(2, int(rng.uniform(0.5, 1.0) * ppm))
        for k, y in enumerate(range(cy - size // 2, cy + size // 2, stripe)):
            c = colour if k % 2 == 0 else accent
            cv2.rectangle(img, (cx - size // 2, y), (cx + size // 2, y + stripe - 1), c, -1)
