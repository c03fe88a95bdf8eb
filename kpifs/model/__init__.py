"""The discrete pupil model and its kernel: apertures, uv sampling, kernel-phase operator,
the field a search can cover.
"""
