"""Deformable mirrors read by a Shack-Hartmann sensor (issue 17): the physics and the estimators.

``mirror`` (the actuators, their influence functions and dynamics), ``shack_hartmann`` (the
subapertures, their spots and the geometry matrix G), ``plans`` (which actuators move together
in each pattern), ``spot_fit`` (the batched spot fitter), ``ladder_fit`` (the spot fit on static
frames of each pattern at a ladder of levels, for spots that change shape as they move), ``demux`` (pattern responses to
actuator columns), ``actuator_fit`` (each actuator's model), ``registration`` (the mirror's
geometry fitted to D0) and ``budget`` (a DM config's run size). Not imported by ``import
torchblur``: import the submodules where they are used.

The DM run itself is the identification's (``torchblur.identify(cfg, rig)`` with a DM config;
:mod:`torchblur.identify.dm_plan`); the simulated DM rig and the contract of a lab's own are in
:mod:`torchblur.rig.dm` and :mod:`torchblur.rig.dm_contract` (docs/dm_rig.md).

Conventions (shared by every module here): N actuators ``j = 0..N-1`` in row-major order of the
actuator grid, positions ``actuator_xy [N, 2]`` in actuator pitches with 0 at the pupil centre
(x to the right, y down, like image columns and rows); M valid subapertures, slopes ordered
``[x of all M, y of all M]`` (2M) in px of spot displacement on the sensor camera; a plan is a
pattern matrix ``patterns [P, N]``: in pattern p actuator j is commanded
``amplitude * patterns[p, j] * sin(omega t)``.
"""
