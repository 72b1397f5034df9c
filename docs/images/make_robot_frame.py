"""Regenerate docs/images/robot_frame.png: the robot-frame convention of every robot kind.

    PYTHONPATH=. python docs/images/make_robot_frame.py

Each panel draws the model's own forward kinematics (jaxcr.kinematics) in the robot frame:
p(0) = 0, the backbone leaving along +z, and the bending direction of the zero bending-plane
joint (phi = 0, delta = 0, alpha = 0) and of a quarter turn of it. The printed tip directions are
what docs/dataset-format.md states.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jaxcr.kinematics import TEST_CTR, ConstantCurvature, SingleSegment, robot_from_dict  # noqa: E402

OUT = Path(__file__).with_name("robot_frame.png")


def bend_direction(p):
    """Unit (x, y) direction of the tip's offset from the z axis."""
    d = np.asarray(p[-1, :2], np.float64)
    return d / np.linalg.norm(d)


def cases():
    cc = ConstantCurvature.make([0.1], [0.003], joints=("kappa", "phi"))
    ss = SingleSegment.make(0.1, 0.003)
    one = dict(TEST_CTR, tubes=TEST_CTR["tubes"][:1])
    ctr = robot_from_dict(dict(one, n_points=33))
    yield (
        "constant_curvature\nq = (kappa, phi), kappa = 12 /m",
        cc,
        [(jnp.array([12.0, 0.0]), "phi = 0"), (jnp.array([12.0, np.pi / 2]), "phi = pi/2")],
    )
    yield (
        "single_segment\nq = (theta_L, delta), theta_L = pi/2 - 1.2",
        ss,
        [
            (jnp.array([np.pi / 2 - 1.2, 0.0]), "delta = 0"),
            (jnp.array([np.pi / 2 - 1.2, np.pi / 2]), "delta = pi/2"),
        ],
    )
    yield (
        "ctr (one tube of TEST_CTR)\nq = (beta_1, alpha_1), beta_1 = -0.3 m",
        ctr,
        [(jnp.array([-0.3, 0.0]), "alpha_1 = 0"), (jnp.array([-0.3, np.pi / 2]), "alpha_1 = pi/2")],
    )


def main():
    fig = plt.figure(figsize=(12, 4.4))
    for k, (title, model, qs) in enumerate(cases()):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        for (q, label), colour in zip(qs, ("tab:blue", "tab:orange"), strict=True):
            p = np.asarray(model.forward(q).centreline.p, np.float64) * 1000.0
            d = bend_direction(p)
            print(f"{model.kind:18s} {label:15s} bends towards (x, y) = ({d[0]:+.3f}, {d[1]:+.3f})")
            ax.plot(p[:, 0], p[:, 1], p[:, 2], colour, lw=2.5, label=label)
        r = 40.0
        for v, name, c in (((r, 0, 0), "x", "r"), ((0, r, 0), "y", "g"), ((0, 0, r), "z", "b")):
            ax.quiver(0, 0, 0, *v, color=c, arrow_length_ratio=0.15)
            ax.text(*(1.15 * np.asarray(v)), name, color=c)
        ax.scatter([0], [0], [0], color="k", s=20)
        ax.text(0, 0, -12, "p(0) = 0", fontsize=8)
        ax.set_xlim(-60, 60)
        ax.set_ylim(-60, 60)
        ax.set_zlim(0, 110)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_zlabel("z (mm)")
        ax.view_init(elev=22, azim=-60)
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=8, loc="upper left")
    fig.suptitle(
        "Robot frame: base at the origin, backbone leaves along +z (units: metres; mm shown)"
    )
    fig.tight_layout()
    fig.savefig(OUT, dpi=90)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
