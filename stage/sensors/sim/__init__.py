"""The simulator: Kinect-faithful virtual sensors watching scripted performers.

    from stage.sensors.sim import Simulator, load_scenario
    sim = Simulator(load_scenario("default"), seed=4)
    rig = sim.rig()                      # exact calibrations (or rig(calibrated=False))
    for capture, sensor, datagram in sim.datagrams(10.0): ...
    stage.app.offline.feed(engine, clock, sim.stream(10.0), until=10.0)  # an in-process engine
    sim.run_realtime(("127.0.0.1", 7770), duration=30)   # over UDP

Scenario files (YAML) describe the rig, the performers' timelines and
events; see docs/sources.md.
"""

from .kinect import KinectModel, VirtualKinect, VirtualPose, ring_poses
from .kinematics import standing_pose
from .performer import Performer, Step
from .scenario import (Event, Scenario, SensorSpec, builtin_names, default_scenario, demo_scenario,
                       load_scenario, parse_scenario)
from .simulator import EPOCH, Datagram, SimSource, Simulator
from .truth import Truth, load_truth, write_truth

__all__ = ["Simulator", "SimSource", "Datagram", "Scenario", "SensorSpec", "Event",
           "Performer", "Step", "KinectModel", "VirtualPose", "VirtualKinect", "ring_poses",
           "standing_pose", "load_scenario", "default_scenario", "demo_scenario",
           "parse_scenario", "builtin_names", "load_truth", "write_truth", "Truth", "EPOCH"]
