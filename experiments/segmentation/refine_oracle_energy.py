"""Is a bad refinement an energy problem or a basin problem? Energy of the found answer vs an
oracle shape fitted to the truth.

For each frame of a synthetic dataset (``jaxcr synth``; needs ``meta.true_cameras`` and the
truth centrelines): refine from the nominal shape (``RefineConfig`` defaults or ``--set``
overrides), fit an *oracle* (delta-u coefficients + camera correction) whose projection with
the dataset's camera matches the true centreline projected with the true camera (2-D least
squares, scipy), refine again warm-started from the oracle, and print the adjusted IoU of
each and the normalised eq. 5 terms (as the solver sees them at full resolution, tau of the
finest level) of the found answer ("cold") and the oracle, evaluated on the same band (the
band tiles of the oracle, then of the cold answer: with ``local`` the outside region is the
band, so terms on different bands are not comparable). If the oracle's data terms plus
regulariser are higher than the cold answer's on the same band, the energy prefers the wrong
shape; if lower, the solver missed it. Also prints mu_in / mu_out (hard masks, band) of both.

    python experiments/segmentation/refine_oracle_energy.py DATASET --frames 006,007 [--set robust=1.0]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize as so

import jaxcr.segmentation.refine as R
from jaxcr.camera import project_points
from jaxcr.io.dataset import load_dataset
from jaxcr.io.images import read_mask
from jaxcr.segmentation.background import colour_mask
from jaxcr.segmentation.energy import chan_vese_energy, pyramid, region_data_from_level
from jaxcr.segmentation.metrics import adjusted_iou
from jaxcr.segmentation.shape import perturbed_centreline, regularisation
from jaxcr.segmentation.silhouette import (
    band_margin,
    level_tube,
    project_tube,
    rasterise_dense,
    select_band,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--frames", required=True, help="comma-separated frame ids")
    ap.add_argument("--camera", default=None)
    ap.add_argument("--set", nargs="*", default=[], help="RefineConfig overrides key=value")
    a = ap.parse_args(argv)
    kw = {}
    for s in a.set:
        k, v = s.split("=", 1)
        kw[k] = eval(v)  # experiment script
    cfg = R.RefineConfig(**kw)
    root = Path(a.dataset)
    ds = load_dataset(root)
    cname = a.camera or next(iter(ds.cameras))
    cam = ds.cameras[cname]
    meta = json.loads((root / "dataset.json").read_text())["meta"]
    T_true = jnp.asarray(meta["true_cameras"][cname], jnp.float32)
    tcam = eqx.tree_at(lambda c: c.T_cam_robot, cam, T_true)
    h, w = cam.height, cam.width
    fn = jax.jit(lambda cl, im, bg: R.refine_frame(cl, (cam,), (im,), (bg,), cfg))
    warm = jax.jit(
        lambda cl, im, bg, c, pc: R.refine_frame(cl, (cam,), (im,), (bg,), cfg, init=c, init_cam=pc)
    )
    lv, tau = cfg.levels[-1], cfg.tau[-1]

    def shape(cl0, p, z_ref):
        ccam = R._corrected_camera(cam, p["cam"][0], z_ref)
        return project_tube(ccam, perturbed_centreline(cl0, p["c"]))

    def terms(cl0, p, pband, im, bg, z_ref):
        data = region_data_from_level(*pyramid(im, bg, lv + 1)[lv], lv, cfg.tile)
        area_ref = R._tube_area(project_tube(cam, cl0), cam)
        lt = level_tube(shape(cl0, p, z_ref), lv, cfg.seg_merge)
        band = select_band(
            level_tube(shape(cl0, pband, z_ref), lv, cfg.seg_merge),
            data.grid,
            cfg.tiles_at(lv),
            cfg.k_seg,
        )
        # candidates of the evaluated shape on the chosen band's tiles (all segments)
        band = eqx.tree_at(
            lambda b: b.segs,
            band,
            jnp.broadcast_to(jnp.arange(lt.ax.shape[0]), (band.tiles.shape[0], lt.ax.shape[0])),
        )
        band = eqx.tree_at(
            lambda b: b.inside, band, select_band(lt, data.grid, cfg.tiles_at(lv), 1).inside
        )
        band = eqx.tree_at(lambda b: b.inside, band, band.inside.at[band.tiles].set(False))
        _, t = chan_vese_energy(
            lt, band, data, 0.0, cfg.weights, tau, area_ref, cfg.local, cfg.robust
        )
        var = data.total_s2 / data.total_w
        reg = cfg.g_reg * regularisation(p["c"], cl0.s) + cfg.g_cam * jnp.sum(p["cam"] ** 2)
        out = {
            "in": cfg.g_in * t["e_in"] / (area_ref * var),
            "out": cfg.g_out * t["e_out"] / (area_ref * var),
            "pen": cfg.g_pen * t["e_pen"] / area_ref,
            "reg": reg,
        }
        out = {k: float(v) for k, v in out.items()}
        out["data+pen"] = out["in"] + out["out"] + out["pen"]
        out["total"] = out["data+pen"] + out["reg"]
        # hard-mask region means on that band
        m = np.asarray(band_margin(lt, data.grid, band) > 0)
        bw, _, img = (np.asarray(x) for x in data.gather(band.tiles))
        cen = np.asarray(data.centre)
        mi = (img[m & (bw > 0)]).mean(0) + cen
        mo = (img[~m & (bw > 0)]).mean(0) + cen
        return out, mi, mo

    def fit_oracle(cl0, truth, z_ref):
        tgt = np.asarray(project_points(tcam, jnp.asarray(truth, jnp.float32))[0])

        def res(x):
            p = {"c": x[:-6].reshape(cfg.coeff_shape), "cam": x[-6:][None]}
            uv = project_points(
                R._corrected_camera(cam, p["cam"][0], z_ref), perturbed_centreline(cl0, p["c"]).p
            )[0]
            return jnp.concatenate([(uv - tgt).ravel(), 0.3 * x])

        f, J = jax.jit(res), jax.jit(jax.jacfwd(res))
        n = int(np.prod(cfg.coeff_shape)) + 6
        sol = so.least_squares(
            lambda x: np.asarray(f(jnp.asarray(x, jnp.float32)), np.float64),
            np.zeros(n),
            jac=lambda x: np.asarray(J(jnp.asarray(x, jnp.float32)), np.float64),
        )
        x = jnp.asarray(sol.x, jnp.float32)
        return {"c": x[:-6].reshape(cfg.coeff_shape), "cam": x[-6:][None]}

    frames = {f.id: f for f in ds.frames}
    for fid in a.frames.split(","):
        f = frames[fid]
        cl0 = ds.robot.forward(jnp.asarray(np.asarray(f.q), jnp.float32)).centreline
        bg, im = colour_mask(jnp.asarray(f.load_image(cname)))
        vis = read_mask(f.masks[cname])
        occ = read_mask(f.occluders[cname]) if f.occluders else np.zeros((h, w), bool)
        truth = np.load(root / f.truth["centreline"], allow_pickle=False)[:, :3]
        z_ref = jnp.mean(cl0.p @ cam.R[2] + cam.t[2])
        r = fn(cl0, im, bg)
        p_cold = {"c": r.coeffs, "cam": R._phys_to_params(r.camera_correction, z_ref)}
        p_or = fit_oracle(cl0, truth, z_ref)
        phys = jnp.concatenate(
            [R.CAM_ROT_UNIT * p_or["cam"][:, :3], R.CAM_T_UNIT * z_ref * p_or["cam"][:, 3:]], 1
        )
        rw = warm(cl0, im, bg, p_or["c"], phys)
        m_or = np.asarray(rasterise_dense(shape(cl0, p_or, z_ref), h, w))

        def adj(m, vis=vis, occ=occ):
            return float(adjusted_iou(np.asarray(m), vis, occ))

        print(
            f"frame {fid}: adjusted IoU nominal {adj(r.nominal_masks[0]):.3f}, cold "
            f"{adj(r.masks[0]):.3f}, oracle fit {adj(m_or):.3f}, warm from oracle "
            f"{adj(rw.masks[0]):.3f}"
        )
        for bname, pb in (("oracle's band", p_or), ("cold answer's band", p_cold)):
            for name, p in (("cold", p_cold), ("oracle", p_or)):
                t, mi, mo = terms(cl0, p, pb, im, bg, z_ref)
                print(
                    f"   {bname:18s} {name:6s} "
                    + " ".join(f"{k} {v:7.3f}" for k, v in t.items())
                    + f"   mu_in {np.round(mi, 3)} mu_out {np.round(mo, 3)}"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
