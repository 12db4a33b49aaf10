"""Robot arm: interface, simulated and Franka backends, station-side safety."""

from remote_site.arm.base import Arm, ArmLimits, ArmReading
from remote_site.arm.registry import ARM_BACKENDS, arm_class, open_arm
from remote_site.arm.safety import CommandResult, SafeArm, SafetyConfig, SafetyCounters

__all__ = ["ARM_BACKENDS", "Arm", "ArmLimits", "ArmReading", "CommandResult", "SafeArm",
           "SafetyConfig", "SafetyCounters", "arm_class", "open_arm"]
