"""The Kinect v2 model: what one sensor reports for the true bodies in front of it.

Numbers and where they come from (defaults of ``KinectModel``; every one can
be changed in a scenario's ``kinect:`` section):

- field of view 70 x 60 degrees and depth range 0.5-4.5 m, 25 joints at about
  30 Hz: seed 003 ("Kinect Sensor": FOV 70 deg horizontally, 60 vertically,
  range of depth sensing 0.5-4.5 m; frames "at a slightly varying frequency of
  about 30 Hz");
- up to six bodies per sensor, user ids 0-5: the K-Multiscope paper (seed 000,
  4.1.1: "a unique identifier from 0 to 5 ... as each Kinect can track up to 6");
- joints turned away from the sensor are biased towards the surface the
  sensor sees, and marked inferred, or not tracked when inference fails:
  seed 003 (self-occlusion, Figure 5 and "Kinect sensor setup");
- recognising a person who enters takes a moment: seed 003 (overlap of
  tracking volumes "needed to recognize a person that enters the volume");
- clocks of separate computers differ by hundreds of milliseconds, sometimes
  seconds: seed 003 ("Hardware & Software Architecture");
- one Kinect system's lag is 60-80 ms: seed 004 ("Deployment of Kinect units");
- occasional NaN frames from a streamer: seed 002.

The noise magnitudes (about 6 mm per axis at 1 m, growing 4 mm per metre,
doubled at ankles and feet) are this model's own assumptions, chosen to match
the engine's smoothing settings (stage.kalman: "Kinect v2 tracked joints
jitter by about 1 cm per axis") at the middle of the range; they are not
measured here. ``bench/bench_sensor_noise.py`` puts them beside real recordings
(N-UCLA, Kinect v1; NTU RGB+D samples and a Kinectron take, Kinect v2): on all
three the real frame-to-frame jitter of the torso and feet is smaller than the
model's, on the NTU samples about 24x at the torso and 21x at the feet at 3.1 m
(docs/sources.md, "Known limits"). The defaults are kept until the lead
decides: every simulated benchmark depends on them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from ...geometry import rot_x, rot_y, rot_z
from ...joints import JOINT_INDEX as J
from ...joints import N_JOINTS, HandState

_FEET = [J[n] for n in ("AnkleLeft", "AnkleRight", "FootLeft", "FootRight")]
_HANDS = [J[n] for n in ("HandLeft", "HandRight", "HandTipLeft", "HandTipRight", "ThumbLeft",
                         "ThumbRight", "WristLeft", "WristRight")]
#: end joints the Kinect gives up on (not tracked) rather than infers when hidden
_FRAGILE = [J[n] for n in ("HandTipLeft", "HandTipRight", "ThumbLeft", "ThumbRight")]
_FRAGILE_HAND = [J[n] for n in ("HandLeft", "HandRight", "HandLeft", "HandRight")]
_TORSO = [J[n] for n in ("SpineBase", "SpineMid", "SpineShoulder")]
#: how much of ``surface_bias_m`` each joint gets: the trunk in full, limbs half
_SURFACE = np.full(N_JOINTS, 0.5)
_SURFACE[[J[n] for n in ("SpineBase", "SpineMid", "SpineShoulder", "Neck", "Head", "HipLeft",
                         "HipRight", "ShoulderLeft", "ShoulderRight")]] = 1.0


def _limb_swap(names: tuple[str, ...]) -> np.ndarray:
    """Joint index map trading the left and right joints of one limb."""
    order = np.arange(N_JOINTS)
    for n in names:
        order[J[n + "Left"]], order[J[n + "Right"]] = J[n + "Right"], J[n + "Left"]
    return order


#: what a limb swap trades: the arms, or the legs; and the joints whose overlap invites it
_LIMB_SWAPS = (_limb_swap(("Elbow", "Wrist", "Hand", "HandTip", "Thumb")),
               _limb_swap(("Knee", "Ankle", "Foot")))
_LIMB_ENDS = ((J["WristLeft"], J["WristRight"]), (J["AnkleLeft"], J["AnkleRight"]))
_SWAP = np.arange(N_JOINTS)
for _name, _i in J.items():
    if _name.endswith("Left"):
        _SWAP[_i], _SWAP[J[_name[:-4] + "Right"]] = J[_name[:-4] + "Right"], _i


@dataclass(frozen=True)
class KinectModel:
    """Parameters of one sensor's behaviour. Angles in degrees, lengths in metres."""

    fov_h: float = 70.0             # seed 003
    fov_v: float = 60.0             # seed 003
    near: float = 0.5               # seed 003
    far: float = 4.5                # seed 003
    fps: float = 30.0               # seed 003 / paper 4.1
    frame_jitter_s: float = 0.002   # s.d. of each frame's capture time about the 30 Hz grid
    pipeline_delay_s: float = 0.060  # the sensor's own pipeline: a frame stamped t shows the
                                    # body as it was at t - this (Kinect v2's ~60 ms; seed 004
                                    # measured 60-80 ms end to end)
    pipeline_jitter_s: float = 0.003  # s.d. of that delay, frame to frame (cut at 3 s.d.)
    drop_p: float = 0.005           # probability that a frame never comes out
    noise_m: float = 0.006          # s.d. per axis of a tracked joint at 1 m
    noise_per_m: float = 0.004      # added to the s.d. per metre beyond 1 m
    noise_correlation: float = 0.6  # frame-to-frame correlation of the noise (AR(1))
    feet_noise: float = 2.0         # factor for ankles and feet
    hands_noise: float = 1.5        # factor for wrists, hands, tips and thumbs
    inferred_noise: float = 2.0     # factor for inferred joints
    fit_bias_m: float = 0.015       # s.d. of a constant per-joint error, drawn per tracked user
    occlusion_bias_m: float = 0.04  # hidden joints are pulled this far towards the sensor
    hand_misread_p: float = 0.08    # a visible hand's state reported wrong
    hand_range_m: float = 3.5       # beyond this distance hand states are 'unknown'
    hand_update_frames: int = 2     # a body's hand states are read every this many frames and
                                    # repeated in between (NTU RGB+D's Kinect v2 takes: every
                                    # second frame, so a misread lasts two; docs/sources.md)
    nan_p: float = 0.001            # a skeleton message sent with NaN coordinates (seed 002)
    glitch_p: float = 0.0           # a tracked joint thrown 0.3-1 m off, still 'tracked' (per
                                    # joint per frame; off by default: for robustness tests)
    acquire_s: float = 0.3          # visible this long before the sensor reports a new user
    lose_s: float = 0.1             # invisible this long before it reports the user lost
    max_users: int = 6              # paper 4.1.1
    mirror_back: bool = False       # report a back-facing body mirrored, as a real Kinect does
    floor_every_s: float = 0.5      # how often /floorPlane is sent (< the 1 s client timeout,
                                    # so a sensor that sees nobody is not taken for silent)
    # -- errors that make real skeletons heavy-tailed (issue 11; tuned so a rigid fit
    #    between two views matches N-UCLA's, see docs/sources.md). Each is drawn only when
    #    it is on, so the ``clean`` preset (all off, fit_bias_m 0.01) reproduces the
    #    earlier, Gaussian-only model number for number.
    surface_bias_m: float = 0.02    # joints fitted this far towards the surface the sensor
                                    # sees (trunk in full, limbs half): a sensor behind the
                                    # person puts hips and shoulders 2x this from one in front
    swap_per_s: float = 0.2         # rate of left/right limb swaps per tracked body, when the
                                    # two wrists (arms) or ankles (legs) overlap in its image
                                    # (x4 side-on)
    swap_s: tuple = (0.2, 1.0)      # how long a swap lasts, s (uniform)
    inferred_off_m: tuple = (0.10, 0.30)  # an inferred joint is guessed this far off (uniform,
                                    # random direction), held while it stays inferred
    take_s: float = 0.0             # the sensor records takes this long (0: one take) ...
    take_gap_s: float = 0.0         # ... this far apart, each sensor's cut starting anywhere

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))

    @classmethod
    def preset(cls, name: str) -> "KinectModel":
        """A named model: 'real' (the defaults) or 'clean' (``PRESETS``)."""
        return replace(cls(), **PRESETS[name])

    def sigma(self, distance: np.ndarray) -> np.ndarray:
        """Noise s.d. per axis (m) of a tracked ordinary joint at ``distance`` metres."""
        return self.noise_m + self.noise_per_m * np.maximum(distance - 1.0, 0.0)

    def joint_factors(self) -> np.ndarray:
        f = np.ones(N_JOINTS)
        f[_FEET] = self.feet_noise
        f[_HANDS] = self.hands_noise
        return f


#: named Kinect models (a scenario's ``kinect: {preset: NAME}``): "real" is the default,
#: tuned on real recordings; "clean" has no heavy tails (no view-dependent bias, limb swaps
#: or guessed joints, the earlier 1 cm fit error): Gaussian noise, occlusion and everything
#: else as "real", for tests and benchmarks that need data a least-squares method is exact on
PRESETS: dict[str, dict] = {
    "real": {},
    "clean": {"surface_bias_m": 0.0, "swap_per_s": 0.0, "inferred_off_m": (0.0, 0.0),
              "fit_bias_m": 0.01},
}


@dataclass(frozen=True)
class VirtualPose:
    """Where a virtual sensor stands and how it is turned (stage space).

    Camera space is the Kinect's: x to the sensor's left, y up, z out of the
    lens. ``yaw``: radians about y (0 looks along +z); ``pitch``: radians the
    sensor is tilted down; ``roll``: radians about its optical axis.
    """

    position: np.ndarray
    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0

    @classmethod
    def looking_at(cls, position, target, roll: float = 0.0) -> "VirtualPose":
        p, q = np.asarray(position, float), np.asarray(target, float)
        d = q - p
        return cls(p, math.atan2(d[0], d[2]), math.atan2(-d[1], math.hypot(d[0], d[2])), roll)

    @property
    def rotation(self) -> np.ndarray:
        """3x3 camera -> stage."""
        return rot_y(self.yaw) @ rot_x(self.pitch) @ rot_z(self.roll)

    @property
    def to_stage(self) -> np.ndarray:
        """4x4 camera space -> stage space."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.position
        return m

    def observe(self, stage_points: np.ndarray) -> np.ndarray:
        """(..., 3) stage points -> camera space."""
        return (np.asarray(stage_points) - self.position) @ self.rotation

    def floor_plane(self) -> np.ndarray:
        """Kinect's FloorClipPlane (a, b, c, d): unit normal in camera space, d = height."""
        normal = self.rotation.T @ np.array([0.0, 1.0, 0.0])
        return np.array([*normal, float(self.position[1])])

    def moved(self, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0,
              move: np.ndarray | None = None) -> "VirtualPose":
        """This pose bumped: angles in radians added, ``move`` metres added."""
        pos = self.position + (np.zeros(3) if move is None else np.asarray(move, float))
        return VirtualPose(pos, self.yaw + yaw, self.pitch + pitch, self.roll + roll)


def ring_poses(count: int = 3, radius: float = 2.5, height: float = 0.8,
               centre: tuple[float, float] = (0.0, 0.0), start_angle: float = 0.0,
               aim_height: float | None = None) -> list[VirtualPose]:
    """``count`` sensors evenly round a circle, all looking at its centre (seed 004's rig).

    Metres, stage space; ``centre`` is (x, z) on the floor. Sensor k stands at
    ``start_angle + 2 pi k / count`` radians round the circle, counted from -z
    towards -x (sensor 0 at ``start_angle = 0`` stands at z = -radius looking
    along +z), ``height`` above the floor, aimed at the centre at
    ``aim_height`` (default: its own height, so it is level). The layout of a
    scenario's ``ring:``.
    """
    aim = height if aim_height is None else aim_height
    cx, cz = centre
    out = []
    for k in range(count):
        a = start_angle + 2 * math.pi * k / count
        position = np.array([cx - radius * math.sin(a), height, cz - radius * math.cos(a)])
        out.append(VirtualPose.looking_at(position, [cx, aim, cz]))
    return out


# Volumes that hide what is behind them: (joint a, joint b, fraction from a to b, radius at 1.75 m)
_SPHERES = (
    ("SpineBase", "SpineBase", 0.0, 0.13), ("SpineBase", "SpineMid", 0.5, 0.15),
    ("SpineMid", "SpineMid", 0.0, 0.15), ("SpineMid", "SpineShoulder", 0.5, 0.15),
    ("SpineShoulder", "SpineShoulder", 0.0, 0.13), ("HipLeft", "HipLeft", 0.0, 0.11),
    ("HipRight", "HipRight", 0.0, 0.11), ("ShoulderLeft", "ShoulderLeft", 0.0, 0.07),
    ("ShoulderRight", "ShoulderRight", 0.0, 0.07), ("Head", "Head", 0.0, 0.10),
    ("Neck", "Neck", 0.0, 0.06),
    ("ShoulderLeft", "ElbowLeft", 0.5, 0.05), ("ShoulderRight", "ElbowRight", 0.5, 0.05),
    ("ElbowLeft", "WristLeft", 0.5, 0.04), ("ElbowRight", "WristRight", 0.5, 0.04),
    ("HipLeft", "KneeLeft", 0.5, 0.09), ("HipRight", "KneeRight", 0.5, 0.09),
    ("KneeLeft", "AnkleLeft", 0.5, 0.06), ("KneeRight", "AnkleRight", 0.5, 0.06),
)
_SA = np.array([J[a] for a, _, _, _ in _SPHERES])
_SB = np.array([J[b] for _, b, _, _ in _SPHERES])
_SF = np.array([f for _, _, f, _ in _SPHERES])[:, None]
_SR = np.array([r for _, _, _, r in _SPHERES])
N_SPHERES = len(_SPHERES)


def body_spheres(joints: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Occluding spheres of a body: (centres (S, 3), radii (S,)), same space as ``joints``."""
    return joints[_SA] + _SF * (joints[_SB] - joints[_SA]), _SR * scale


@dataclass
class Visibility:
    """What a sensor can see of each body this frame (all arrays per body)."""

    in_view: np.ndarray        # (P,) bool: the body is in the field of view and range
    in_fov: np.ndarray         # (P, 25) bool
    hidden_self: np.ndarray    # (P, 25) bool: behind the body's own limbs or torso
    hidden_other: np.ndarray   # (P, 25) bool: behind another performer
    visible_fraction: np.ndarray = field(default_factory=lambda: np.zeros(0))


def visibility(model: KinectModel, cam: np.ndarray, scales: np.ndarray,
               margin: float = 0.03) -> Visibility:
    """Field of view, range and occlusion for P bodies in camera space, ``cam`` (P, 25, 3).

    A joint is hidden when the line from the lens to it passes through a
    body sphere that lies in front of it (by at least the sphere's radius
    plus ``margin``, so a joint is never hidden by the limb it belongs to).
    """
    p_count = len(cam)
    x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
    tan_h = math.tan(math.radians(model.fov_h / 2))
    tan_v = math.tan(math.radians(model.fov_v / 2))
    in_fov = (z > 0.05) & (np.abs(x) <= tan_h * z) & (np.abs(y) <= tan_v * z)
    centre = cam[:, J["SpineMid"]]
    in_view = in_fov[:, J["SpineMid"]] & (centre[:, 2] >= model.near) & (centre[:, 2] <= model.far)
    hidden_self = np.zeros((p_count, N_JOINTS), dtype=bool)
    hidden_other = np.zeros((p_count, N_JOINTS), dtype=bool)
    if p_count:
        centres, radii, owner = [], [], []
        for k in range(p_count):
            c, r = body_spheres(cam[k], scales[k])
            centres.append(c)
            radii.append(r)
            owner.append(np.full(len(r), k))
        C = np.concatenate(centres)                  # (M, 3)
        R = np.concatenate(radii)                    # (M,)
        O = np.concatenate(owner)                    # (M,)
        P = cam.reshape(-1, 3)                       # (N, 3)
        pp = np.einsum("nk,nk->n", P, P)
        norm_p = np.sqrt(pp)
        cp = C @ P.T                                 # (M, N)
        t = np.clip(cp / np.maximum(pp, 1e-12), 0.0, 1.0)
        cc = np.einsum("mk,mk->m", C, C)
        d2 = cc[:, None] - 2.0 * t * cp + t * t * pp
        in_front = t * norm_p < norm_p - (R[:, None] + margin)
        blocks = (d2 < (R * R)[:, None]) & in_front  # (M, N)
        joint_owner = np.repeat(np.arange(p_count), N_JOINTS)
        same = O[:, None] == joint_owner[None, :]
        hidden_self = (blocks & same).any(axis=0).reshape(p_count, N_JOINTS)
        hidden_other = (blocks & ~same).any(axis=0).reshape(p_count, N_JOINTS)
    seen = in_fov & ~hidden_other
    return Visibility(in_view, in_fov, hidden_self, hidden_other, seen.mean(axis=1)
                      if p_count else np.zeros(0))


def body_visible(vis: Visibility, k: int) -> bool:
    """Whether the sensor can track body ``k`` at all this frame."""
    return bool(vis.in_view[k] and vis.visible_fraction[k] >= 0.5
                and not vis.hidden_other[k, _TORSO].all())


class UserTrack:
    """A sensor's tracking of one performer: acquisition, loss, its noise state."""

    def __init__(self, rng: np.random.Generator, model: KinectModel) -> None:
        self.visible_since: float | None = None
        self.invisible_since: float | None = None
        self.tracked = False
        self.noise = rng.standard_normal((N_JOINTS, 3))
        self.bias = rng.normal(0.0, model.fit_bias_m, (N_JOINTS, 3))
        self.inferred = np.zeros(N_JOINTS, dtype=bool)   # inferred in the last frame
        self.guess = np.zeros((N_JOINTS, 3))             # the offset of each inferred joint
        self.swap_frames = 0                             # frames of limb swap left
        self.swap_joints: np.ndarray | None = None       # which joints trade places
        self.hand_frames = 0                             # frames reported so far
        self.hands_read: tuple | None = None             # the hand states last read

    def hands(self, seen: tuple, model: KinectModel) -> tuple:
        """The hand states this frame reports: ``seen`` (read now) on every
        ``hand_update_frames``-th frame of the track, the last ones read in between."""
        every = max(int(model.hand_update_frames), 1)
        if self.hands_read is None or self.hand_frames % every == 0:
            self.hands_read = seen
        self.hand_frames += 1
        return self.hands_read

    def update(self, visible: bool, t: float, model: KinectModel) -> bool:
        """Advance the state machine; True while the sensor reports this body."""
        if visible:
            self.invisible_since = None
            if self.visible_since is None:
                self.visible_since = t
            if not self.tracked and t - self.visible_since >= model.acquire_s - 1e-9:
                self.tracked = True
        else:
            self.visible_since = None
            if self.tracked:
                if self.invisible_since is None:
                    self.invisible_since = t
                if t - self.invisible_since >= model.lose_s - 1e-9:
                    self.tracked = False
        return self.tracked


def measure(model: KinectModel, track: UserTrack, rng: np.random.Generator, cam: np.ndarray,
            in_fov: np.ndarray, hidden_self: np.ndarray, hidden_other: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray]:
    """The reported (joints (25, 3) camera space, conf (25,)) for one tracked body."""
    hidden = hidden_self | hidden_other
    conf = np.where(in_fov, np.where(hidden, 0.5, 1.0), 0.0)
    # the Kinect loses a hand's tip and thumb first: when they or their hand are hidden
    hand_hidden = conf[_FRAGILE_HAND] < 1.0
    conf[_FRAGILE] = np.where(hidden[_FRAGILE] | ~in_fov[_FRAGILE] | hand_hidden, 0.0,
                              conf[_FRAGILE])
    rho = model.noise_correlation
    track.noise = rho * track.noise + math.sqrt(max(1.0 - rho * rho, 0.0)) * \
        rng.standard_normal((N_JOINTS, 3))
    distance = np.linalg.norm(cam, axis=1)
    sigma = model.sigma(distance) * model.joint_factors()
    sigma = np.where(conf < 1.0, sigma * model.inferred_noise, sigma)
    joints = cam + sigma[:, None] * track.noise + track.bias
    # a depth camera sees the near surface: hidden joints are fitted towards it (seed 003)
    toward = cam / np.maximum(distance, 1e-6)[:, None]
    joints = joints - (hidden[:, None] * model.occlusion_bias_m) * toward
    joints = _heavy_tails(model, track, rng, cam, joints, distance, toward, hidden, conf)
    if model.glitch_p > 0:  # drawn only when asked for, so other runs keep their numbers
        hit = (rng.random(N_JOINTS) < model.glitch_p) & (conf > 0)
        if hit.any():
            direction = rng.normal(size=(int(hit.sum()), 3))
            direction /= np.linalg.norm(direction, axis=1, keepdims=True)
            joints[hit] += direction * rng.uniform(0.3, 1.0, (int(hit.sum()), 1))
    return joints, conf


def _heavy_tails(model: KinectModel, track: UserTrack, rng: np.random.Generator,
                 cam: np.ndarray, joints: np.ndarray, distance: np.ndarray, toward: np.ndarray,
                 hidden: np.ndarray, conf: np.ndarray) -> np.ndarray:
    """The view-dependent bias, guessed inferred joints and limb swaps (see KinectModel)."""
    if model.surface_bias_m > 0:
        joints = joints - (model.surface_bias_m * _SURFACE * ~hidden)[:, None] * toward
    lo, hi = model.inferred_off_m
    if hi > 0:
        new = hidden & ~track.inferred & (conf > 0)
        if new.any():
            d = rng.normal(size=(int(new.sum()), 3))
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            track.guess[new] = d * rng.uniform(lo, hi, (int(new.sum()), 1))
        track.inferred = hidden & (conf > 0)
        joints = joints + track.guess * track.inferred[:, None]
    if model.swap_per_s > 0:
        if track.swap_frames <= 0:
            # a depth camera mixes up a left and a right limb that overlap in its image, most
            # of all when the body is side-on: |lateral axis . line of sight|
            lateral = cam[J["ShoulderLeft"]] - cam[J["ShoulderRight"]]
            norm = float(np.linalg.norm(lateral)) or 1.0
            side = abs(float(lateral @ toward[J["SpineMid"]])) / norm
            close = [k for k, (a, b) in enumerate(_LIMB_ENDS)
                     if np.linalg.norm(cam[a, :2] - cam[b, :2]) < 0.3]
            if close and rng.random() < model.swap_per_s * (1.0 + 3.0 * side) / model.fps:
                lo_s, hi_s = model.swap_s
                track.swap_frames = max(1, int(round(rng.uniform(lo_s, hi_s) * model.fps)))
                track.swap_joints = _LIMB_SWAPS[close[int(rng.integers(len(close)))]]
        if track.swap_frames > 0 and track.swap_joints is not None:
            track.swap_frames -= 1
            joints = joints[track.swap_joints]
    return joints


class VirtualKinect:
    """One virtual sensor measuring true skeletons the caller poses: the Kinect model alone.

    For tests and benchmarks that script the bodies (and the sensor: assign
    ``pose`` to bump it) frame by frame. Each call measures exactly as the
    simulator's sensors do: field of view and range, occlusion by the bodies'
    own and each other's limbs, correlated noise, a constant fit error per
    user, hidden joints inferred and pulled towards the lens, glitches. Time
    is the caller's: there is no frame clock, acquisition delay, dropped or
    NaN frame, clock or hand state here (the ``Simulator`` adds those).
    Seeded: the same calls give the same numbers.
    """

    def __init__(self, pose: VirtualPose, model: KinectModel | None = None,
                 rng: np.random.Generator | int = 0) -> None:
        self.pose = pose
        self.model = model or KinectModel()
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self._tracks: dict[int, UserTrack] = {}

    def observe(self, truth: np.ndarray, user: int = 0,
                ) -> tuple[np.ndarray, np.ndarray] | None:
        """One body alone (nobody else hides it): ``truth`` (25, 3) stage space, metres ->
        (joints (25, 3) camera space, metres; conf (25,)), or None when the sensor cannot
        track it (outside the view or range, or mostly hidden). ``user`` keeps each
        body's noise and fit error apart when several are observed one by one."""
        return self._measure([user], np.asarray(truth, float)[None])[0]

    def observe_all(self, bodies: list[np.ndarray],
                    ) -> list[tuple[np.ndarray, np.ndarray] | None]:
        """Several bodies in one frame, hiding each other: ``observe`` for each, in order
        (body k is user k)."""
        if not len(bodies):
            return []
        return self._measure(list(range(len(bodies))), np.stack(bodies).astype(float))

    def _measure(self, users: list[int], stage: np.ndarray) -> list:
        cam = self.pose.observe(stage)
        # body size from the upper body, which no pose stretches (rest: 0.55 m at 1.75 m)
        scales = np.linalg.norm(stage[:, J["Neck"]] - stage[:, J["SpineBase"]], axis=1) / 0.55
        vis = visibility(self.model, cam, scales)
        out: list[tuple[np.ndarray, np.ndarray] | None] = []
        for k, user in enumerate(users):
            if not body_visible(vis, k):
                self._tracks.pop(user, None)  # found again later: a new fit error, as on a Kinect
                out.append(None)
                continue
            track = self._tracks.get(user)
            if track is None:
                track = self._tracks[user] = UserTrack(self.rng, self.model)
            out.append(measure(self.model, track, self.rng, cam[k], vis.in_fov[k],
                               vis.hidden_self[k], vis.hidden_other[k]))
        return out


def sensed_hand(model: KinectModel, rng: np.random.Generator, true: HandState, conf: float,
                distance: float) -> HandState:
    """The hand state a sensor reports for one hand."""
    if conf <= 0.0:
        return HandState.NOT_TRACKED
    if conf < 1.0 or distance > model.hand_range_m or true < HandState.OPEN:
        return HandState.UNKNOWN if true >= HandState.OPEN else true
    if rng.random() < model.hand_misread_p:
        others = [s for s in (HandState.OPEN, HandState.CLOSED, HandState.LASSO) if s != true]
        return others[int(rng.integers(len(others)))]
    return true


def faces_away(cam: np.ndarray) -> bool:
    """Whether a body (camera space) has its back to the sensor."""
    left = cam[J["HipLeft"]] - cam[J["HipRight"]] + cam[J["ShoulderLeft"]] - cam[J["ShoulderRight"]]
    # facing = left turned a quarter towards the right about y; the lens looks along +z,
    # so a body facing the sensor has facing.z < 0
    facing_z = left[0]
    return facing_z > 0.05


def mirrored(joints: np.ndarray, conf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left and right swapped, as a Kinect reports a person seen from behind."""
    return joints[_SWAP], conf[_SWAP]
