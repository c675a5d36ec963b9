"""Reduction algorithms applied to simulated raw ramps (validation of the simulated effects)."""
