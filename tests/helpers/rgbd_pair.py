"""Two organised RGB-D views of one scene, the source shifted along camera x (shared by the
projective-ICP and colour-term tests)."""

import jax.numpy as jnp
import numpy as np

from jaxcr.registration.icp import CloudArrays
from jaxcr.registration.projective import depth_image


def shifted_pair(view, K, shift: float = 0.003):
    """``view(shift_x) -> (P, C, N, ok)`` organised arrays. Returns the source cloud (valid
    pixels of ``view(shift)``), the target and source depth images, and the true source ->
    target transform (a translation by ``shift`` in x)."""
    Pt, Ct, Nt, okt = view(0.0)
    Ps, Cs, Ns, oks = view(shift)
    tgt = depth_image(Pt, Ct, Nt, okt, K)
    src_img = depth_image(Ps, Cs, Ns, oks, K)
    ok = oks.reshape(-1)
    src = CloudArrays(
        *(jnp.asarray(a.reshape(-1, 3)[ok], jnp.float32) for a in (Ps, Cs, Ns)),
        jnp.ones(int(ok.sum()), bool),
    )
    T_true = np.eye(4)
    T_true[0, 3] = shift
    return src, tgt, src_img, T_true
