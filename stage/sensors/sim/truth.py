"""Ground truth written alongside a simulated recording, for tests and benchmarks.

File: NumPy ``.npz`` with ``t`` (N,) simulation seconds (recording clock),
``names`` (P,) performer names, ``joints`` (N, P, 25, 3) float32 metres in
stage space (NaN while a performer is offstage), ``hands`` (N, P, 2) int8
hand-state codes (-1 offstage), ``sensors`` (S,) ids and ``to_stage``
(S, 4, 4) their true poses at t = 0, and ``meta`` (JSON text: scenario,
seed, events).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from ...joints import N_JOINTS


@dataclass
class Truth:
    t: np.ndarray
    names: list[str]
    joints: np.ndarray
    hands: np.ndarray
    sensors: list[str]
    to_stage: np.ndarray
    meta: dict

    def at(self, t: float) -> dict[str, np.ndarray]:
        """Joints of each performer on stage at the sample nearest ``t``."""
        k = int(np.clip(np.searchsorted(self.t, t), 0, len(self.t) - 1))
        if k > 0 and abs(self.t[k - 1] - t) < abs(self.t[k] - t):
            k -= 1
        return {name: self.joints[k, i].astype(float) for i, name in enumerate(self.names)
                if not np.isnan(self.joints[k, i, 0, 0])}


def write_truth(sim, path: str, duration: float, rate: float = 30.0, t0: float = 0.0) -> int:
    """Sample ``sim.truth`` at ``rate`` Hz over [0, duration); returns the sample count.

    ``t0``: added to the stored times (the engine-clock start of a fed run).
    """
    times = np.arange(0.0, duration, 1.0 / rate)
    names = [p.name for p in sim.performers]
    joints = np.full((len(times), len(names), N_JOINTS, 3), np.nan, dtype=np.float32)
    hands = np.full((len(times), len(names), 2), -1, dtype=np.int8)
    for k, t in enumerate(times):
        for i, performer in enumerate(sim.performers):
            state = performer.state(float(t))
            if state is not None:
                joints[k, i] = state[0]
                hands[k, i] = [int(state[1][0]), int(state[1][1])]
    poses = sim.sensor_poses(0.0)
    meta = {"scenario": sim.scenario.name, "seed": sim.seed, "rate": rate,
            "events": [{"at": e.at, "kind": e.kind, "target": e.target}
                       for e in sim.scenario.events]}
    with open(path, "wb") as f:
        np.savez_compressed(f, t=times + t0, names=np.array(names), joints=joints, hands=hands,
                            sensors=np.array(list(poses)),
                            to_stage=np.stack([p.to_stage for p in poses.values()]),
                            meta=np.array(json.dumps(meta)))
    return len(times)


def load_truth(path: str) -> Truth:
    with np.load(path, allow_pickle=False) as z:
        return Truth(z["t"], [str(n) for n in z["names"]], z["joints"], z["hands"],
                     [str(s) for s in z["sensors"]], z["to_stage"], json.loads(str(z["meta"])))
