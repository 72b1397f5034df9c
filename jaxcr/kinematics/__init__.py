"""Robot kinematic models mapping joint values q to a sampled centreline."""

from jaxcr.kinematics.cosserat import (
    Centreline,
    integrate_centreline,
    integrate_steps,
    perturb_centreline,
)

__all__ = ["Centreline", "integrate_centreline", "integrate_steps", "perturb_centreline"]
