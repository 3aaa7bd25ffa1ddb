"""Cone-beam geometry values, rigid transforms and sphere-shadow models."""

from .cone import ConeGeometry
from .rotations import axis_angle, rotvec_to_matrix, matrix_to_rotvec
from .sphere import shadow_bias, shadow_centroid, shadow_conic, shadow_ellipse
from .transforms import RigidTransform

__all__ = ["ConeGeometry", "RigidTransform", "axis_angle", "rotvec_to_matrix", "matrix_to_rotvec",
           "shadow_bias", "shadow_centroid", "shadow_conic", "shadow_ellipse"]
