"""Helpers for stage's tests and benchmarks; never used by the product at run time.

``jack``: a dummy JACK server for MIDI tests and the MIDI benchmark.
``script``: scripted fused frames (``ScriptedStage``) for piece tests.
``simdata``: simulated sensor streams with known calibrations, for the
calibration tests and benchmark. ``walks``: walks (a set gait, or the CMU
motion capture) watched by seed 003's six-sensor walkway, for the gait tests
and benchmark. Both build their bodies and sensors with
the simulator (``stage.sensors.sim``), the one synthetic body and sensor
model of stage.
"""
