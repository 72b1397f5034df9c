"""``trace_stereo_tips`` with traces placed by the capsule end fit (docs/decisions.md S42): a
view marked ``cap_from_image`` keeps its own end-face length, the other view gets the one
from the tube's 3-D direction, ``half_width |u . v|`` (closed form on a pinhole rig)."""

from types import SimpleNamespace

import numpy as np

from jaxcr.stereo.pipeline import trace_stereo_tips

K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])


def _rig():
    T1 = np.eye(4)
    a = np.radians(15.0)
    T2 = np.eye(4)
    T2[:3, :3] = np.array([[np.cos(a), 0, -np.sin(a)], [0, 1, 0], [np.sin(a), 0, np.cos(a)]])
    T2[:3, 3] = [-0.08, 0.0, 0.01]
    return [SimpleNamespace(K=K, dist=np.zeros(5), T_cam_robot=T) for T in (T1, T2)]


def _px(T, P):
    x = T[:3, :3] @ P + T[:3, 3]
    return (K @ (x / x[2]))[:2]


def test_cap_from_image_is_kept_and_the_other_view_uses_the_axis():
    cams = _rig()
    P = np.array([0.01, -0.005, 0.3])  # the tip (end face's centre), metres
    u = np.array([0.6, 0.3, -0.74])
    u /= np.linalg.norm(u)
    hw = 6.0
    traces, expect = [], []
    for c in cams:
        T = c.T_cam_robot
        tip = _px(T, P)
        d = _px(T, P + 0.002 * u) - tip
        d /= np.linalg.norm(d)
        ray = T[:3, :3].T @ np.linalg.solve(K, np.r_[tip, 1.0])
        ray /= np.linalg.norm(ray)
        expect.append(hw * abs(u @ ray))  # the end face's length seen along the ray
        # The silhouette's end at tip + a d, the one-view cap 1 px (not a).
        traces.append(SimpleNamespace(tip=tip + (expect[-1] - 1.0) * d, cap_px=1.0, end_dir=d,
                                      end_half_width_px=hw, true_tip=tip))  # fmt: skip
    tips, a = trace_stereo_tips(cams, traces)
    # Orthographic approximation at the tip in end_face_lengths: 0.05 px on this rig.
    np.testing.assert_allclose(a, expect, atol=0.05)
    for t, tip in zip(traces, tips, strict=True):
        np.testing.assert_allclose(tip, t.true_tip, atol=0.05)
    traces[0].cap_from_image = True
    tips2, a2 = trace_stereo_tips(cams, traces)
    assert a2[0] == 1.0
    np.testing.assert_allclose(tips2[0], traces[0].tip, atol=1e-9)
    np.testing.assert_allclose(tips2[1], tips[1], atol=1e-12)
