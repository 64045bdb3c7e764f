"""Synthetic range images and camera frames with ground truth, and their evaluation.

Scores after Hoover et al. (1996).
"""
