"""Dataset importers: other skeleton formats into stage recordings.

- ``ntu``: NTU RGB+D ``.skeleton`` files (Kinect v2; several cameras of one
  performance become one multi-sensor recording).
- ``nucla``: Northwestern-UCLA multiview JSON (Kinect v1, 20 joints).
- ``bvh``: BVH motion capture (also used by the simulator's performers).

Each parser is written from the format's published description and tested on
small files the tests generate in that format.
"""
