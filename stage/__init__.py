"""stage: music and dance performance with multi-sensor body tracking.

Sensors (Kinect-style skeleton clients) send OSC to the engine, which
calibrates them into one stage space, fuses each person across sensors,
smooths with a Kalman filter and hands the fused bodies to views.
"""

__version__ = "0.1.0"

#: The distribution's name for pip and importlib.metadata ("stage" on PyPI is another
#: project); the import package and the command are ``stage``.
DISTRIBUTION = "stage-kuatro"


def install_hint(extra: str) -> str:
    """How to add an optional extra, for one-line errors: ``install_hint("webcam")``."""
    return f"pip install '{DISTRIBUTION}[{extra}]' (in a checkout: pip install -e '.[{extra}]')"
