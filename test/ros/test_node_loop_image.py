"""`loop_closure/image` through a real DDS graph: an accepted loop's query | match picture with
its inlier matches, a rejected best candidate's with loop_image_rejected, none when off."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from bag_fixtures import textured
from node_harness import wait_for

from pair_vpr_ros.messages.loop_image import PANEL_HEIGHT

BANNER = 42  # px above the two images (messages.loop_image)
SIDE = PANEL_HEIGHT * 160 // 120  # each 160 x 120 image drawn 240 px high
ACCEPTED, REJECTED = [40, 120, 40], [40, 40, 150]  # banner colours, BGR


@pytest.fixture(scope="module")
def places():
    return [textured(seed) for seed in range(3)]  # 160 x 120, corners for features


def picture(msg) -> np.ndarray:
    assert (msg.encoding, msg.step) == ("bgr8", 3 * msg.width)
    image = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width, 3)
    assert image.shape == (BANNER + PANEL_HEIGHT, 2 * SIDE + 4, 3)
    return image


def drawn(rgb: np.ndarray) -> np.ndarray:
    return cv2.resize(rgb, (SIDE, PANEL_HEIGHT))[:, :, ::-1].astype(int)


def test_loop_image_shows_query_match_and_inliers(harness, places):
    h = harness(geometric_verification=True, min_inliers=8, relative_pose=False)
    h.publish([places[0], places[1], places[2], places[0]])  # keyframe 3 revisits keyframe 0
    h.processed(4)
    wait_for(lambda: len(h.got["loop_closure/image"]) == 1)
    msg = h.got["loop_closure/image"][0]
    assert (msg.header.stamp.sec, msg.header.frame_id) == (103, "cam")
    image = picture(msg)
    assert image[5, 5].tolist() == ACCEPTED
    # verified: the inlier matches are drawn across both images (in the palette's colours)
    line = np.all(image[BANNER:] == [80, 220, 80], axis=2)
    assert line[:, :SIDE].sum() > 20 and line[:, SIDE + 4 :].sum() > 20


def test_rejected_candidates_and_switching_it_off(harness, places):
    h = harness()
    h.publish([places[0], places[1], places[2]])
    h.processed(3)
    assert h.got["loop_closure/image"] == []  # rejected best candidates: off by default
    assert h.set(loop_image_rejected=True)[0].successful
    h.publish([places[0]], t0=104.0)  # revisit of keyframe 0 (accepted), image
    h.publish([textured(9)], t0=105.0)  # a new place: its best candidate is rejected, image
    h.processed(5)
    wait_for(lambda: len(h.got["loop_closure/image"]) == 2)
    accepted, rejected = (picture(m) for m in h.got["loop_closure/image"])
    assert (accepted[5, 5].tolist(), rejected[5, 5].tolist()) == (ACCEPTED, REJECTED)
    # not verified, so no lines: the match side is keyframe 0's kept image (JPEG), not another
    # place's and not the grey panel of a missing image
    match, query = accepted[BANNER:, SIDE + 4 :].astype(int), accepted[BANNER:, :SIDE]
    same, other = (np.abs(match - drawn(places[i])).mean() for i in (0, 1))
    assert same < 0.3 * other and np.abs(query - drawn(places[0])).mean() < 1  # the query
    assert h.set(loop_image=False)[0].successful
    h.publish([places[2]], t0=106.0)  # a loop, but no image now
    h.processed(6)
    wait_for(lambda: h.node.stats.counts.loops == 2)
    assert len(h.got["loop_closure/image"]) == 2
