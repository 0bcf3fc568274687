"""Views as plugins: the interface, the loader and the host.

    from stage.views import View, ViewHost

    class Hello(View):
        def on_frame(self, frame):
            ...

A view receives fused frames, piece events and engine status on its own
thread; the host keeps slow or broken views away from the engine. Views are
installed through the entry-point group ``stage.views.v1`` (the built-in ones,
in the folder ``plugins/`` installed as ``stage_plugins``, exactly like
third-party ones). Reference and tutorial: docs/views.md.
"""

from .base import API_VERSION, GROUP, Scene, SensorStatus, Status, View, ViewContext
from .host import MONITOR_PORT, ViewHost
from .loader import PluginInfo, discover_all, discover_views
from .status import sensor_health

__all__ = ["API_VERSION", "GROUP", "MONITOR_PORT", "PluginInfo", "Scene", "SensorStatus",
           "Status", "View", "ViewContext", "ViewHost", "discover_all", "discover_views",
           "sensor_health"]
