"""Tele-Touch remote palpation station: arm, phantom, visuotactile sensor, stiffness, agent."""
