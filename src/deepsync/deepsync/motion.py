"""How the receiver moves, by name: the motion models a user picks with ``motion``.

A motion model sets what the tracker assumes of the receiver (how fast its velocity may
change, how fast it may be going when a track starts, how wide a site's bias may be) and how long the sync stage may stack
frames: a stack is one position, so it may be as long as the receiver stays within a small
part of a sample (156 m at 1.92 MS/s) and of the bias decorrelation distance, and longer
stacks hear weaker sites (each doubling gains about 3 dB). Sliding stacks (a new stack every
``hop_frames``) keep the answers coming at 10 Hz or more whatever the length.

Neutral ground (it imports only ``deepsync.schema``): the sync stage, fusion, the pipeline, the
command line and the ROS parameters all read the one registry here, and the one ``MOTION``
setting (its help and choices) the command line's flag and the nodes' parameter are made from.
"""

from __future__ import annotations

from dataclasses import dataclass

from deepsync.schema import Setting


@dataclass(frozen=True)
class MotionModel:
    """One way of moving: the tracker's process model and the stacks it allows."""

    name: str
    assumes: str  # what it assumes, in a sentence
    acceleration_std_mps2: float  # velocity random walk: m/s gained or lost per second, 1-sigma
    initial_speed_std_mps: float  # speed prior (1-sigma per axis) when a track starts
    n_frames: int  # frames (10 ms) per stack
    hop_frames: int  # frames from one stack's start to the next
    multipath_std_m: float  # the stationary sigma of a site's NLOS bias state (fusion)
    prior_hold_s: float  # how long an initial position holds a track that the sites cannot yet fix
    # whether a start without an initial position waits for a site more than the unknowns where
    # the tower database has one (with D + 1 sites a false lock fits exactly)
    spare_site_at_start: bool = True

    @property
    def summary(self) -> str:
        """What it assumes and the stacks it allows: the command line's and the nodes' help."""
        return f"{self.assumes} ({self.n_frames}-frame stacks every {self.hop_frames})"

    @property
    def stack_seconds(self) -> float:
        return self.n_frames * 0.01


MOTION_MODELS: dict[str, MotionModel] = {
    model.name: model for model in (
        # 0.5 m/s^2: a walker's stops, starts and turns (1.4 m/s gained or lost in about 2 s)
        # without letting one range's noise pull the track about. One second of stack is 1.4 m
        # walked: nothing next to a sample or to the 40 m over which a site's bias changes.
        # A walker keeps a site's pull for half a minute, long enough for an anchor to measure
        # it: a 100 m bias sigma lets it, where 60 m held the pulls of the ray-traced old town
        # (up to 215 m) as position error, overconfident (docs/design/fusion.md, the route set).
        MotionModel("pedestrian", "a person walking (or a slow robot): up to ~2 m/s, turns and stops within seconds",
                    acceleration_std_mps2=0.5, initial_speed_std_mps=2.0, n_frames=100, hop_frames=20,
                    multipath_std_m=100.0, prior_hold_s=30.0),
        # 3 m/s^2: town driving (0-50 km/h in 5 s, braking, a corner at 15 m/s on a 75 m
        # radius). Half a second of stack is 7.5 m at 15 m/s: a twentieth of a sample.
        # A car crosses the pulls in seconds and its bias states take fresh variance at that
        # pace: at 100 m its track grows too vague for its odometry ever to align (the statistical
        # drives lose the odometry's 33-66 % off the p90) and a sixth of its poses; 60 m keeps
        # both, though the ray-traced old town's pulls then leave it overconfident (NEES 5-70).
        MotionModel("vehicle", "a car or a fast robot: up to ~30 m/s, accelerating, braking and cornering at a few m/s^2",
                    acceleration_std_mps2=3.0, initial_speed_std_mps=20.0, n_frames=50, hop_frames=10,
                    multipath_std_m=60.0, prior_hold_s=30.0),
        # 0.01 m/s^2: an asset that stands (its position wanders by centimetres per minute in
        # the model, enough for the linearisation); stacks of 2 s hear sites 3 dB below 1 s.
        # It never moves to tell its sites' pulls from its position, so a 100 m sigma leaves
        # its track too vague to publish; 60 m is already cautious (NEES 0.2-0.3 without GNSS). Where it stands
        # stays where it was put: an initial position or a GNSS fix holds its track for an hour
        # on the one or two sites a city gives it (the route set's static asset with a start pose:
        # a pose in 24 % of the stacks at 30 s, as a walker's, 99 % at 5 / 5 m). It starts from
        # three sites: where it stands it rarely hears a fourth (the route set's: never), so the
        # spare site would leave it to its stacks' own three-site fixes, which have no spare
        # either; its track holds between them (route set, no anchor: a pose after the first in
        # 55-63 % of the stacks at 20 / 29-32 m, with a three-site start 100 % at 18-19 / 24-26 m).
        MotionModel("static", "an asset that does not move (a parked container, a fixed sensor)",
                    acceleration_std_mps2=0.01, initial_speed_std_mps=0.2, n_frames=200, hop_frames=50,
                    multipath_std_m=60.0, prior_hold_s=3600.0, spare_site_at_start=False),
    )
}
DEFAULT_MOTION = "pedestrian"
MOTION = Setting("motion", str, "How the receiver moves, which sets the stacks and the tracker's motion model.",
                 choices=MOTION_MODELS)


def motion_model(name: str) -> MotionModel:
    """The motion model called ``name``; ValueError listing the names."""
    try:
        return MOTION_MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(f"motion {name!r} is not one of {', '.join(MOTION_MODELS)}") from None
