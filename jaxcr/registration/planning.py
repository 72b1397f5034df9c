"""Algorithm 1 of the paper: planning and execution of the arm motion around the target.

The planner keeps the chain of planned arcs (one per mobilised path piece) and the
arclength the tip has travelled on the current arc. After each sensing it

1. plans the first arc when there is none;
2. otherwise tries to *update* the current arc: a flatter (smaller |kappa|) and longer arc
   from the same start that is collision-free in the updated map;
3. when updating fails and the tip reached the end of the current arc, plans a *new* arc,
   tangent-continuous at the end of the current one;
4. reports "no motion" when no collision-free arc exists, "arm limit" when the path would
   need more sections than the arm has;
5. otherwise moves the tip forward by ``delta_s`` along the (updated or new) arc.

Candidate arcs come from a (kappa, length) grid, checked in one batched call
(:func:`jaxcr.registration.collision.batch_clearance_kdtree`, or the dense JAX
:func:`jaxcr.registration.collision.batch_clearance` with ``PlannerConfig.collision="jax"``). An arc is admissible when it is
collision-free, keeps at least ``min_range`` from the object centre, ends within
``band`` of the viewing radius ``view_radius`` and roughly tangent to the circle about the
object in the winding direction; among admissible arcs the one whose end winds furthest
around the object is chosen (the object is watched by turning the tip camera).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from jaxcr.registration.arm import Arc, ArmLimit, ArmSpec, arc_points_np, conform_sections
from jaxcr.registration.collision import (
    batch_clearance,
    batch_clearance_kdtree,
    collision_free,
)


@dataclass(frozen=True)
class PlannerConfig:
    """Planner parameters (SI). ``direction`` +1 winds counter-clockwise, -1 clockwise."""

    direction: int
    delta_s: float
    view_radius: float
    band: float = 0.05
    min_range: float = 0.1
    clearance: float = 0.01
    tangent_tol: float = 0.6
    n_kappa: int = 25
    n_length: int = 10
    cloud_size: int = 512
    # Clearance check: "kdtree" (:func:`batch_clearance_kdtree`, numpy + scipy k-d tree,
    # default) or "jax" (:func:`batch_clearance`, the dense batched check; the reference).
    collision: str = "kdtree"


@dataclass
class PlanState:
    arcs: list[Arc] = field(default_factory=list)
    travelled: list[float] = field(default_factory=list)
    status: str = "moving"
    planning_time: float = 0.0  # seconds, all steps (the paper's Table I T_mp per route)
    events: list[str] = field(default_factory=list)
    step_times: list[float] = field(default_factory=list)  # seconds, one per step


def _winding(xy: np.ndarray, centre: np.ndarray) -> np.ndarray:
    return np.arctan2(xy[..., 1] - centre[1], xy[..., 0] - centre[0])


def _pad(cloud: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    if len(cloud) > size:
        idx = np.linspace(0, len(cloud) - 1, size).astype(int)
        cloud = cloud[idx]
    out = np.zeros((size, 3), np.float32)
    out[: len(cloud)] = cloud
    mask = np.zeros(size, bool)
    mask[: len(cloud)] = True
    return out, mask


def _first_per_cell(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices of the first point in each ``cell``-sized voxel, ordered by voxel
    (lexicographic in (x, y, z) cell index): ``np.unique(cells, axis=0,
    return_index=True)[1]`` on one int64 key per point (a 1-D sort, ~10x cheaper than the
    row-wise unique)."""
    c = np.floor(points / cell).astype(np.int64)
    c -= c.min(axis=0)
    n = c.max(axis=0) + 1
    key = (c[:, 0] * n[1] + c[:, 1]) * n[2] + c[:, 2]  # lexicographic order preserved
    return np.unique(key, return_index=True)[1]


class ArcPlanner:
    """Algorithm 1 (see module docstring). ``step(cloud, centre)`` plans and moves once."""

    def __init__(self, spec: ArmSpec, cfg: PlannerConfig):
        self.spec = spec
        self.cfg = cfg
        self.state = PlanState()
        if cfg.collision not in ("kdtree", "jax"):
            raise ValueError(f"collision must be 'kdtree' or 'jax', got {cfg.collision!r}")
        if cfg.collision == "kdtree":
            return
        # Compile the batched check once, outside the timed planning (Table I's T_mp).
        b = cfg.n_kappa * cfg.n_length
        batch_clearance(
            np.zeros((b, 3), np.float32),
            np.zeros(b, np.float32),
            np.ones(b, np.float32),
            np.zeros((cfg.cloud_size, 3), np.float32),
            np.zeros(cfg.cloud_size, bool),
            np.float32(0.0),
        ).block_until_ready()

    # ----------------------------------------------------------------- candidate search
    def _candidates(self, start, max_len, cloud, centre, kappa_max=None, min_len=0.0):
        cfg, spec = self.cfg, self.spec
        kmax = spec.max_kappa if kappa_max is None else kappa_max
        ks = np.linspace(-kmax, kmax, cfg.n_kappa)
        lo = max(min_len, cfg.delta_s)
        if max_len < lo:
            return None
        ls = np.linspace(lo, max_len, cfg.n_length)
        K, L = np.meshgrid(ks, ls, indexing="ij")
        K, L = K.ravel(), L.ravel()
        starts = np.broadcast_to(np.asarray(start, np.float32), (K.size, 3))
        # Only points within reach of the arm's swept tube (it moves in the plane z = height)
        # can collide; dropping the others keeps the batched check small.
        near = cloud[np.abs(cloud[:, 2] - spec.height) < spec.radius + cfg.clearance]
        if len(near):  # one point per 5 mm cell is plenty against a >= 25 mm margin
            near = near[_first_per_cell(near, 0.005)]
        pts, mask = _pad(near, cfg.cloud_size)
        # numpy float32 arguments straight into the jitted check (converting with
        # jnp.asarray(x, jnp.float32) compiles a cast on first use, inside the timed T_mp).
        args = (
            np.ascontiguousarray(starts),
            K.astype(np.float32),
            L.astype(np.float32),
            pts,
            mask,
            np.float32(spec.height),
        )
        if cfg.collision == "kdtree":
            # clearances beyond twice the threshold are not needed exactly (pruned searches)
            bound = 2.0 * (spec.radius + cfg.clearance)
            clear = batch_clearance_kdtree(*args, upper_bound=bound)
        else:
            clear = np.asarray(batch_clearance(*args))
        free = np.asarray(collision_free(clear, spec.radius, cfg.clearance))
        # Geometry of the candidates (planar, numpy-sized: b x 16 samples).
        s = np.linspace(0.0, 1.0, 16)[None, :] * L[:, None]
        st = arc_points_np(np.asarray(start, np.float64), K, s)
        r = np.hypot(st[..., 0] - centre[0], st[..., 1] - centre[1])
        end = st[:, -1]
        r_end = r[:, -1]
        radial = np.arctan2(end[:, 1] - centre[1], end[:, 0] - centre[0])
        tangent = radial + cfg.direction * np.pi / 2
        dh = np.angle(np.exp(1j * (end[:, 2] - tangent)))
        w0 = _winding(np.asarray(start)[None, :2], centre)[0]
        prog = cfg.direction * np.angle(np.exp(1j * (radial - w0)))
        ok = (
            free
            & (r.min(axis=1) >= cfg.min_range)
            & (np.abs(r_end - cfg.view_radius) <= cfg.band)
            & (np.abs(dh) <= cfg.tangent_tol)
            & (prog > 0)
        )
        return K, L, ok, prog

    def _section_budget(self, upto: int) -> float:
        """Arclength still available for arcs from index ``upto`` on (all sections)."""
        used = sum(self.state.travelled[:upto])
        return self.spec.n_sections * self.spec.max_length - used

    def _plan_from(self, start, cloud, centre, budget):
        res = self._candidates(
            start, min(budget, 0.9 * np.pi * self.cfg.view_radius), cloud, centre
        )
        if res is None:
            return None
        K, L, ok, prog = res
        if not ok.any():
            return None
        score = np.where(ok, prog - 1e-3 * np.abs(K), -np.inf)
        j = int(np.argmax(score))
        return Arc(tuple(float(v) for v in start), float(K[j]), float(L[j]))

    def _update(self, cloud, centre):
        st = self.state
        cur = st.arcs[-1]
        budget = self._section_budget(len(st.arcs) - 1)
        res = self._candidates(
            cur.start,
            min(budget, 0.9 * np.pi * self.cfg.view_radius),
            cloud,
            centre,
            kappa_max=abs(cur.kappa) * 0.999,
            min_len=cur.length * 1.001,
        )
        if res is None:
            return None
        K, L, ok, prog = res
        ok &= np.sign(K) * np.sign(cur.kappa) >= 0
        ok &= L >= st.travelled[-1] + self.cfg.delta_s
        if not ok.any():
            return None
        score = np.where(ok, -np.abs(K) + 1e-3 * L, -np.inf)  # flattest, then longest
        j = int(np.argmax(score))
        return Arc(cur.start, float(K[j]), float(L[j]))

    # ----------------------------------------------------------------- Algorithm 1
    def step(self, cloud: np.ndarray, centre: np.ndarray) -> str:
        """One iteration of Algorithm 1 with the sensed ``cloud`` (world, m) and the current
        object-centre estimate ``centre``; returns the status: "moving", "no motion" or
        "arm limit"."""
        st = self.state
        t0 = time.perf_counter()
        spec = self.spec
        if not st.arcs:
            arc = self._plan_from(spec.base, cloud, centre, self._section_budget(0))
            if arc is None:
                st.status = "no motion"
            else:
                st.arcs, st.travelled = [arc], [0.0]
                st.events.append("plan first arc")
        else:
            arc = self._update(cloud, centre)
            if arc is not None:
                st.arcs[-1] = arc
                st.events.append("update arc")
            elif st.travelled[-1] + self.cfg.delta_s > st.arcs[-1].length + 1e-9:
                end = st.arcs[-1].state_at(st.travelled[-1])
                new = self._plan_from(end, cloud, centre, self._section_budget(len(st.arcs)))
                if new is None:
                    st.status = "no motion"
                else:
                    st.arcs[-1] = Arc(st.arcs[-1].start, st.arcs[-1].kappa, st.travelled[-1])
                    st.arcs.append(new)
                    st.travelled.append(0.0)
                    st.events.append("new arc")
            else:
                st.events.append("keep arc")
        if st.status == "moving":
            st.travelled[-1] = min(st.travelled[-1] + self.cfg.delta_s, st.arcs[-1].length)
            try:
                conform_sections(st.arcs, st.travelled, spec)
            except ArmLimit:
                st.travelled[-1] -= self.cfg.delta_s
                st.status = "arm limit"
        dt = time.perf_counter() - t0
        st.planning_time += dt
        st.step_times.append(dt)
        return st.status

    def sections(self) -> tuple[np.ndarray, np.ndarray]:
        return conform_sections(self.state.arcs, self.state.travelled, self.spec)

    def tip_state(self) -> np.ndarray:
        st = self.state
        if not st.arcs:
            return np.asarray(self.spec.base, np.float64)
        return st.arcs[-1].state_at(st.travelled[-1])
