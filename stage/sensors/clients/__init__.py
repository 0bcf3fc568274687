"""Clients for real sensors, and the sensor-independent parts they share.

- ``stage.clients.osc``: the Client-to-Server API as a client speaks it (user
  slots 0-5, one bundle per frame with a capture-time timetag).
- ``stage.clients.webcam``: any webcam through MediaPipe pose (extra ``webcam``).
- ``stage.clients.kinect2``: Kinect v2 through the Kinect SDK 2.0 (Windows, extra ``kinect2``).
- ``stage.clients.azure``: Azure Kinect / Orbbec Femto body tracking (extra ``azure``).

The sensor libraries are imported only when a client runs, never at import time.
"""
