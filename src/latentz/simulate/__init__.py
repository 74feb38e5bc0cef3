"""Simulated microscope, calibration stacks and gear movies with ground truth."""
