"""stage's built-in views, registered through the ``stage.views.v1`` entry points
exactly like a third-party plugin (see pyproject.toml and docs/views.md).

The folder is ``plugins/`` in the repository; it installs as ``stage_plugins``
(``package-dir`` in pyproject.toml), so it never clashes with another top-level
``plugins``. Inside, modules import each other relatively.

- ``stage_plugins.midi``: notes, controls and programs to MIDI ports or a Standard MIDI File;
- ``stage_plugins.osc``: the Server-to-View API and piece events to named OSC targets;
- ``stage_plugins.relay``: fused bodies to another stage server, as one more sensor;
- ``stage_plugins.monitor``: the live web monitor for installers and performers.

Nothing here is imported by ``stage`` itself: the host finds these through the
installed distribution's metadata.
"""
