"""Demo world depth: points on facades, the ground and cars land on pixels of their depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pair_vpr_ros.demo import generate_world
from pair_vpr_ros.demo.camera import Camera, project, to_camera
from pair_vpr_ros.demo.depth import depth_to_mm, render_depth
from pair_vpr_ros.demo.layout import Facade, Layout, Occluder

CAM = Camera(width=160, height=120)


def one_facade(p0=(10.0, 5.0), p1=(10.0, -5.0), height=12.0) -> Layout:
    """A single building front at x = 10, facing -x (towards the origin)."""
    facade = Facade(0, p0, p1, height, 0)
    return Layout(0, np.zeros(2), np.zeros(2), np.zeros((1, 4)), [facade])


def facade_points(facade: Facade, n: int = 9) -> np.ndarray:
    """[n*n, 3] world points on the facade, inset from its edges."""
    t, z = np.meshgrid(np.linspace(0.05, 0.95, n), np.linspace(0.3, facade.height - 0.3, n))
    p0, p1 = np.array(facade.p0), np.array(facade.p1)
    xy = p0 + (p1 - p0) * t.reshape(-1, 1)
    return np.c_[xy, z.reshape(-1)]


def inverse_depth_at(depth: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Bilinear 1/depth at sub-pixel positions [K, 2] (exact for a plane) -> depth [K]."""
    u0, v0 = np.floor(px[:, 0]).astype(int), np.floor(px[:, 1]).astype(int)
    a, b = px[:, 0] - u0, px[:, 1] - v0
    with np.errstate(divide="ignore"):
        inv = 1.0 / depth.astype(np.float64)  # sky pixels (0) become inf, unused below
    mix = (
        inv[v0, u0] * (1 - a) * (1 - b)
        + inv[v0, u0 + 1] * a * (1 - b)
        + inv[v0 + 1, u0] * (1 - a) * b
        + inv[v0 + 1, u0 + 1] * a * b
    )
    return 1.0 / mix


def visible(px: np.ndarray, pc: np.ndarray, margin: float = 1.0) -> np.ndarray:
    return (
        (pc[:, 2] > CAM.near)
        & (px[:, 0] >= margin)
        & (px[:, 0] <= CAM.width - 1 - margin)
        & (px[:, 1] >= margin)
        & (px[:, 1] <= CAM.height - 1 - margin)
    )


def test_head_on_facade_points_land_on_pixels_of_their_depth():
    layout = one_facade()
    pose = np.array([0.0, 0.0, 0.0])  # looking along +x at the facade 10 m away
    depth = render_depth(layout, pose, CAM)
    pc = to_camera(facade_points(layout.facades[0]), pose, CAM)
    px = project(pc, CAM)
    ok = visible(px, pc)
    assert ok.sum() > 30
    pix = np.round(px[ok]).astype(int)
    np.testing.assert_allclose(depth[pix[:, 1], pix[:, 0]], pc[ok, 2], atol=0.01)
    assert pc[ok, 2] == pytest.approx(10.0)


@pytest.mark.parametrize("yaw_deg", [-35.0, 20.0])
def test_oblique_facade_points_match_their_camera_z(yaw_deg):
    layout = one_facade(p0=(12.0, 15.0), p1=(6.0, -15.0), height=20.0)
    pose = np.array([-2.0, 1.0, math.radians(yaw_deg)])
    depth = render_depth(layout, pose, CAM)
    pc = to_camera(facade_points(layout.facades[0], 15), pose, CAM)
    px = project(pc, CAM)
    ok = visible(px, pc)
    assert ok.sum() > 30
    np.testing.assert_allclose(inverse_depth_at(depth, px[ok]), pc[ok, 2], atol=0.01)


def test_back_of_a_facade_is_not_seen_and_sky_is_zero():
    layout = one_facade()
    behind = render_depth(layout, np.array([20.0, 0.0, math.pi]), CAM)  # sees its back
    ground_rows = np.arange(CAM.height) > CAM.cy
    assert (behind[~ground_rows] == 0).all()  # sky: nothing above the horizon
    assert (behind[ground_rows] > 0).all()  # only ground below it
    wide_low = one_facade(p0=(10.0, 30.0), p1=(10.0, -30.0), height=8.0)
    front = render_depth(wide_low, np.zeros(3), CAM)
    assert front[0].max() == 0.0  # the top row looks over the 8 m facade into the sky
    assert (front[int(CAM.cy)] > 0).all()  # the horizon row sees the facade everywhere


def test_ground_points_in_the_world_land_on_their_depth():
    world = generate_world(3, frames=60, width=CAM.width, height=CAM.height)
    pose = world.poses[5]
    depth = render_depth(world.layout, pose, CAM, world.occluders_of(5))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    ahead = np.array([[pose[0] + r * c, pose[1] + r * s, 0.0] for r in (3.0, 5.0, 8.0)])
    pc = to_camera(ahead, pose, CAM)
    px = project(pc, CAM)
    np.testing.assert_allclose(inverse_depth_at(depth, px), pc[:, 2], atol=0.01)


def test_a_car_side_lands_on_its_depth_in_front_of_the_facade():
    layout = one_facade(height=12.0)
    car = Occluder("car", 6.0, 0.0, math.pi / 2, (200, 30, 30), (4.4, 1.8, 1.6))
    pose = np.zeros(3)
    depth = render_depth(layout, pose, CAM, [car])
    # The side facing the camera is 0.9 m in front of the car's centre line, at body height.
    side = np.array([[6.0 - 0.9, y, 0.45] for y in (-1.0, 0.0, 1.0)])
    pc = to_camera(side, pose, CAM)
    px = project(pc, CAM)
    np.testing.assert_allclose(inverse_depth_at(depth, px), pc[:, 2], atol=0.01)
    far_car = Occluder("car", 200.0, 0.0, 0.0, (0, 0, 0), (4.4, 1.8, 1.6))
    no_car = render_depth(layout, pose, CAM)
    assert (depth < no_car).sum() > 50
    # Beyond the colour renderer's occluder range: not drawn, so no depth either.
    np.testing.assert_array_equal(render_depth(layout, pose, CAM, [far_car]), no_car)


def test_person_billboard_has_the_depth_of_its_centre():
    layout = one_facade()
    person = Occluder("person", 5.0, 0.0, 0.0, (10, 200, 10), (0.5, 0.5, 1.8))
    depth = render_depth(layout, np.zeros(3), CAM, [person])
    pc = to_camera(np.array([[5.0, 0.0, 1.0]]), np.zeros(3), CAM)
    u, v = np.round(project(pc, CAM)[0]).astype(int)
    assert depth[v, u] == pytest.approx(5.0)


def test_max_range_and_millimetres():
    layout = one_facade()
    depth = render_depth(layout, np.zeros(3), CAM, max_range=8.0)
    assert depth.dtype == np.float32 and depth.shape == (CAM.height, CAM.width)
    assert depth.max() <= 8.0 and (depth[int(CAM.cy)] == 0).all()  # facade at 10 m: cut
    mm = depth_to_mm(np.array([[0.0, 1.2346, np.nan, 70.0, -1.0]]))
    assert mm.dtype == np.uint16
    np.testing.assert_array_equal(mm, [[0, 1235, 0, 0, 0]])
