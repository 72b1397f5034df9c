"""Algorithm 1's planning time is recorded per step (issue 18: the paper reports 20-31 ms per
step; the pipeline kept only the route's total). Contract: one entry per ``step`` call, all
positive, summing to ``planning_time`` (the same timer). Small planner grid and cloud so the
batched clearance check compiles in a fraction of the pipeline's size."""

import numpy as np
import pytest

from jaxcr.registration.arm import ArmSpec
from jaxcr.registration.planning import ArcPlanner, PlannerConfig


def test_planning_time_is_recorded_per_step():
    spec = ArmSpec(3, 0.15, 0.01, 0.1, (0.3, -0.1, np.pi / 2), 12.0)
    cfg = PlannerConfig(
        direction=1, delta_s=0.02, view_radius=0.3, n_kappa=5, n_length=4, cloud_size=64
    )
    planner = ArcPlanner(spec, cfg)
    cloud = np.zeros((0, 3))
    steps = 0
    for _ in range(4):
        steps += 1
        if planner.step(cloud, np.zeros(2)) != "moving":
            break
    st = planner.state
    assert len(st.step_times) == steps
    assert all(t > 0 for t in st.step_times)
    # the same perf_counter differences summed in the same order: equal to rounding
    assert sum(st.step_times) == pytest.approx(st.planning_time, rel=1e-12)
