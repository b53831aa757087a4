"""The exoskeleton's rigid-body model (URDF + Pinocchio): HIP kinematics, dynamics, capsules."""

from .model import (
    HOME_CONFIGURATION,
    JointLimits,
    LinkCapsule,
    RobotModel,
    default_urdf_path,
    parse_link_capsules,
)

__all__ = [
    "HOME_CONFIGURATION",
    "JointLimits",
    "LinkCapsule",
    "RobotModel",
    "default_urdf_path",
    "parse_link_capsules",
]
