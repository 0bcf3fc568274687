"""Helpers for stage's tests and benchmarks; never used by the product at run time.

``script``: scripted fused frames (``ScriptedStage``) for piece tests. It
builds its bodies with the simulator's kinematics (``stage.sensors.sim``),
the one synthetic body and sensor model of stage.
"""
