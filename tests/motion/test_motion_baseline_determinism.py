"""The grabCut baseline is deterministic (issue 17 item 9): grabCut's GMMs start from
k-means++ centres drawn from OpenCV's global RNG, so the same frames gave masks differing by
up to hundreds of pixels depending on what had used that RNG before."""

import cv2
import numpy as np
import pytest

from jaxcr.io.motion_dataset import load_motion_dataset
from jaxcr.motion.baseline import fitzpatrick_segment, ml_graphcut
from jaxcr.motion.run import first_touch, touch_frames_u8
from jaxcr.synth.motion_scenes import generate_motion_video


@pytest.fixture(scope="module")
def touch_frames(tmp_path_factory):
    # pushed_static seed 0 at 160x120, 10 px/frame: before the fix, 5 of 8 RNG states gave a
    # different threshold-40 mask (6-378 px of ~230)
    d = tmp_path_factory.mktemp("bl") / "push"
    generate_motion_video(d, "pushed_static", seed=0, size=(160, 120), n_frames=12, speed_px=10)
    ds = load_motion_dataset(d)
    return touch_frames_u8(ds, first_touch(ds))


@pytest.mark.parametrize("threshold", [20.0, 40.0])
def test_baseline_mask_does_not_depend_on_the_global_rng(touch_frames, threshold):
    masks = []
    for state in (1, 7920, 15839, 39596, 12345):
        cv2.setRNGSeed(state)  # what any other OpenCV user may have left behind
        cv2.randu(np.zeros((4, 4)), 0, 1)
        masks.append(fitzpatrick_segment(*touch_frames, threshold=threshold))
    assert masks[0].any()
    for m in masks[1:]:
        np.testing.assert_array_equal(m, masks[0])


def test_ml_graphcut_does_not_depend_on_the_global_rng(touch_frames):
    image = touch_frames[2]
    change = np.abs(touch_frames[2].astype(int) - touch_frames[1].astype(int)).max(2) > 40
    masks = []
    for state in (3, 99, 2024):
        cv2.setRNGSeed(state)
        masks.append(ml_graphcut(image, change))
    for m in masks[1:]:
        np.testing.assert_array_equal(m, masks[0])
