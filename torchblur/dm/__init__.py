"""Deformable mirrors read by a Shack-Hartmann sensor (issue 17): the physics and the estimators
(docs/deformable_mirrors.md; the layer: docs/architecture.md). Not imported by ``import
torchblur``: import the submodules where they are used.

Conventions (shared by every module here): N actuators ``j = 0..N-1`` in row-major order of the
actuator grid, positions ``actuator_xy [N, 2]`` in actuator pitches with 0 at the pupil centre
(x to the right, y down, like image columns and rows); M valid subapertures, slopes ordered
``[x of all M, y of all M]`` (2M) in px of spot displacement on the sensor camera; a plan is a
pattern matrix ``patterns [P, N]``: in pattern p actuator j is commanded
``amplitude * patterns[p, j] * sin(omega t)``.
"""
