"""Tele-Touch local haptic station: XYZ platform, ArrayTac display, tactile renderer, agent."""
