"""Deformable mirrors seen by a Shack-Hartmann sensor (issue 17)."""
