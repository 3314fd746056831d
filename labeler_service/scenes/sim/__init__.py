"""The articulated multi-person simulator behind ``mocap-labeler simulate``.

``body`` (segments, joints, markers, forward kinematics), ``motion`` (walk / hug / pile joint
angle and root trajectories), ``occlusion`` (soft-tissue wobble, jitter, proximity-driven gaps,
ghost points). :func:`labeler_service.scenes.simulate.simulate_scene` wires them together.

Kept free of imports: the ``simulate`` command and the benchmarks read :data:`SCENARIOS` for
their argument choices without loading numpy or scipy.
"""

#: What the simulated performers do (see :mod:`.motion`).
SCENARIOS = ("walk", "hug", "pile")
