"""Margins of tests/segmentation/test_refine.py::test_two_cameras_recover_the_out_of_plane_bend
with the suite's two-camera program (refine_scene.RIG_CFG) over six render-noise seeds: error
ratios two views / one view and two views / nominal, both views' mask IoU, the correction.

    JAX_PLATFORMS=cpu PYTHONPATH=. python experiments/segmentation/twocam_rig_margins.py

Results: experiments/results/segmentation/twocam_rig_margins.md.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxcr.camera import Camera
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.metrics import iou, mean_centreline_error
from jaxcr.segmentation.refine import refine_frame, refine_frame_jit
from jaxcr.segmentation.shape import perturbed_centreline
from tests.helpers import refine_scene as rs
from tests.helpers.tube_render import render_tube


def main():
    base, cam_a = rs.base(), rs.camera()
    W, H = rs.W, rs.H
    cam_b = Camera.look_at([0, -0.3, 0], [0, 0, 0], [0, 0, 1], fx=200.0, size=(W, H))
    truth = perturbed_centreline(
        base, jnp.asarray([[0.05, 0.0, 0.0], [0.35, -0.1, 0.0]], jnp.float32)
    )
    run = eqx.filter_jit(refine_frame)
    rig = rs.RIG_CFG
    for s in (20, 120, 220, 320, 420, 520):
        views = []
        for k, cam in enumerate((cam_a, cam_b)):
            img, mask = render_tube(truth, cam, s + k, (W, H))
            bg, ip = colour_mask(jnp.asarray(img))
            views.append((ip, bg, mask))
        two = run(
            base,
            (cam_a, cam_b),
            tuple(v[0] for v in views),
            tuple(v[1] for v in views),
            rig,
            jnp.zeros(rig.coeff_shape),
            True,
            jnp.zeros((2, 6)),
        )
        one = refine_frame_jit(base, cam_a, views[0][0], views[0][1], rs.CFG)
        e2 = float(mean_centreline_error(two.centreline.p, truth.p))
        e1 = float(mean_centreline_error(one.centreline.p, truth.p))
        en = float(mean_centreline_error(base.p, truth.p))
        ious = [float(iou(two.masks[k], views[k][2])) for k in range(2)]
        print(
            s,
            f"e2/e1={e2 / e1:.3f} e2/en={e2 / en:.3f} ious={ious[0]:.3f},{ious[1]:.3f} ok={bool(two.ok)} cam={np.round(np.asarray(two.camera_correction), 4).tolist()}",
            flush=True,
        )


if __name__ == "__main__":
    main()
