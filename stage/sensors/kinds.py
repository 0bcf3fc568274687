"""What the engine knows of each kind of sensor, by the type its client registers with
(``/registerDevice``; the rig's ``type`` for a sensor that does not say)."""

from __future__ import annotations

#: the frames a sensor of each type repeats one hand-state reading over: a Kinect v2 reads
#: hands every second frame (all 36 inner runs of the NTU RGB+D samples are an even number
#: of frames, docs/sources.md); the project's webcam client classifies them in every frame
#: (``stage.sensors.clients.webcam``). The engine counts a report as 1 / this of a reading
#: (``stage.engine.hands``); the simulator's sensors of the type read them so
HAND_READING_FRAMES = {"kinect2": 2, "webcam-mediapipe": 1}
#: a type not listed (a client that did not register, a third party's): taken for a Kinect
#: v2, whose repeats would otherwise count as new evidence
DEFAULT_HAND_READING_FRAMES = 2
