"""stage's built-in views, registered through the ``stage.views.v1`` entry points
exactly like a third-party plugin (see pyproject.toml and docs/views.md).

- ``plugins.midi``: notes, controls and programs to MIDI ports or a Standard MIDI File;
- ``plugins.osc``: the Server-to-View API and piece events to named OSC targets;
- ``plugins.relay``: fused bodies to another stage server, as one more sensor;
- ``plugins.monitor``: the live web monitor for installers and performers.

Nothing here is imported by ``stage`` itself: the host finds these through the
installed distribution's metadata.
"""
