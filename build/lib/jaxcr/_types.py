"""Shared jaxtyping aliases for array shapes used across jaxcr."""

from jaxtyping import Array, Bool, Float, Int

Vec3 = Float[Array, "3"]
Mat3 = Float[Array, "3 3"]
Mat4 = Float[Array, "4 4"]
Points = Float[Array, "n 3"]

__all__ = ["Array", "Bool", "Float", "Int", "Vec3", "Mat3", "Mat4", "Points"]
