"""Accuracy of a stereo reconstruction against ground truth (synthetic sets).

* backbone RMS: distance of every reconstructed point (0.5 mm spacing) to the dense true
  backbone (nearest point, k-d tree), root mean square; plus the maximum and the
  coverage (reconstructed arclength over true arclength);
* diameters: per segment, the relative error of the segment's median diameter;
* boundaries: 3-D distance of each detected boundary to the true one (matched in order);
* plane angles: per segment, the absolute error of the angles with the X-Y, Z-X, Y-Z planes;
* curvature: per segment, relative error of the arc fit's curvature.

Segments are compared only when the number found equals the true number; otherwise the
frame's ``segments_ok`` is False and per-segment errors are absent.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["evaluate_frame"]


def evaluate_frame(result: dict, truth: dict) -> dict:
    """Errors of one reconstructed frame (``reconstruct_pair`` output) against the truth
    arrays written by :mod:`jaxcr.synth.stereo_ctr` (metres; errors in mm, %, degrees)."""
    tp = np.asarray(truth["p"])
    d, _ = cKDTree(tp).query(np.asarray(result["p"]))
    out = {
        "backbone_rms_mm": 1e3 * float(np.sqrt(np.mean(d**2))),
        "backbone_max_mm": 1e3 * float(d.max()),
        "coverage": float((result["s"][-1]) / truth["s"][-1]),
        "tip_error_mm": 1e3 * float(np.linalg.norm(result["p"][-1] - tp[-1])),
    }
    k_true = len(truth["seg_diameter"])
    segs = result["segments"]
    out["n_segments"] = len(segs)
    out["n_segments_true"] = k_true
    out["segments_ok"] = len(segs) == k_true
    if not out["segments_ok"]:
        return out
    out["diameter_err_pct"] = [
        100.0 * (s["diameter_mm"] * 1e-3 / dt - 1.0)
        for s, dt in zip(segs, truth["seg_diameter"], strict=True)
    ]
    out["boundary_err_mm"] = [
        1e3 * float(np.linalg.norm(bp - bt))
        for bp, bt in zip(result["boundary_p"], truth["boundary_p"], strict=True)
    ]
    out["plane_angle_err_deg"] = [
        [abs(s[k] - a) for k, a in zip(("phi_xy_deg", "phi_zx_deg", "phi_yz_deg"), at, strict=True)]
        for s, at in zip(segs, truth["seg_plane_angles"], strict=True)
    ]
    out["curvature_err_pct"] = [
        100.0 * (s["curvature_1pm"] / kt - 1.0)
        for s, kt in zip(segs, truth["seg_curvature"], strict=True)
    ]
    out["length_err_mm"] = [
        s["length_mm"] - 1e3 * lt for s, lt in zip(segs, truth["seg_length"], strict=True)
    ]
    return out
