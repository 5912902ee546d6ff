"""Anytime mapping: when a live stream's frames are integrated and when the map is optimised.

H2-Mapping's geometry comes from the octree and its SDF priors, which a single frame's depth fills in; the
optimisation only sharpens them. So in real-time mode every frame that arrives is integrated (rays, voxels,
priors, colour prior, observed cells, keyframe decision; `Mapper.add_frame`) and optimisation steps run in the time
left between frames (`Mapper.live_step`, on the newest frame and its coverage-selected keyframes), instead of a
fixed number of steps per frame that makes a 30 Hz stream drop most of its frames.

`AnytimeSchedule` makes the decision (integrate the waiting frame, or take a step) from the seconds each costs and
the frames waiting, so that integration comes first (a stream integration keeps up with loses no frame) while
optimisation keeps at least `opt_share` of the mapping thread's time when integration is not catching up.
`FusionStride` decides whether a frame fuses its depth into every fine-prior lattice in view or, while other frames
wait, only into its new voxels' (every `anytime.fine_prior_stride`-th frame still fuses whole). `Plateau` ends the
optimisation after the stream ends once the loss stops improving. None of them measures time itself: callers pass
the seconds in (tests drive them with a fake clock).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from h2viz.config import AnytimeConfig
from h2viz.errors import ConfigError


class Action(str, Enum):
    INTEGRATE = "integrate"  # integrate the oldest waiting frame
    STEP = "step"  # one optimisation step
    WAIT = "wait"  # nothing to do: no frame waiting and nothing to optimise (or optimisation has settled)


class Phase(str, Enum):
    """What the anytime mapper is doing, as the dashboard shows it."""

    STREAMING = "streaming"  # frames arriving; steps between them
    SHARPENING = "sharpening"  # the stream ended or paused; optimisation goes on over the keyframes
    SETTLED = "settled"  # the loss stopped improving (or the time limit was reached); nothing runs
    STOPPED = "stopped"  # the user stopped the optimisation


def check_anytime(cfg: AnytimeConfig) -> None:
    """ConfigError naming the anytime.* field that is out of range."""
    if not 0.0 <= cfg.opt_share < 1.0:
        raise ConfigError(f"anytime.opt_share must lie in [0, 1), got {cfg.opt_share}")
    if cfg.backlog_frames < 1:
        raise ConfigError(f"anytime.backlog_frames must be >= 1, got {cfg.backlog_frames}")
    if cfg.catch_up_frames < 1:
        raise ConfigError(f"anytime.catch_up_frames must be >= 1, got {cfg.catch_up_frames}")
    if cfg.plateau_window < 1 or cfg.plateau_patience < 1:
        raise ConfigError("anytime.plateau_window and anytime.plateau_patience must be >= 1")
    if cfg.plateau_tol < 0.0 or cfg.sharpen_max_s < 0.0:
        raise ConfigError("anytime.plateau_tol and anytime.sharpen_max_s must be >= 0")
    if cfg.fine_prior_stride < 1:
        raise ConfigError(f"anytime.fine_prior_stride must be >= 1, got {cfg.fine_prior_stride}")


class AnytimeSchedule:
    """Integration first, with optimisation owed `opt_share` of the mapping time unless integration is catching up.

    Every integration of c seconds makes optimisation owed c * share / (1 - share) seconds. A waiting frame is
    integrated unless a step is owed; a step taken while one is owed pays its seconds off, and what it overpays
    (a step is longer than what one frame owes) is credit the next integrations use first. With no frame waiting,
    steps run freely and bank nothing, so that when frames come faster again they are integrated at once.

    Catching up: with `catch_up` or more frames waiting (but fewer than a full `backlog`), frames are integrated
    whatever is owed, so a stream that integration alone keeps up with loses no frame to the backlog; steps then
    take the time integration leaves (they resume as soon as fewer frames wait), and those integrations owe none.
    When integration cannot keep up even alone, the backlog fills, frames are dropped anyway, and steps keep a
    share of the time so that the map is still optimised.
    """

    def __init__(self, opt_share: float, catch_up: int = 3, backlog: int = 30) -> None:
        if not 0.0 <= opt_share < 1.0:
            raise ConfigError(f"anytime.opt_share must lie in [0, 1), got {opt_share}")
        if not 1 <= catch_up:
            raise ConfigError(f"anytime.catch_up_frames must be >= 1, got {catch_up}")
        self.ratio = opt_share / (1.0 - opt_share)
        self.catch_up, self.backlog = int(catch_up), int(backlog)
        self.owed_s = 0.0  # > 0: step time owed; < 0: credit from a step that overpaid
        self._catching_up = False  # the last decision was made catching up
        self.integrated = 0
        self.steps = 0
        self.integrate_s = 0.0
        self.step_s = 0.0

    def next(self, waiting: int, can_step: bool) -> Action:
        """What to do now: `waiting` frames wait to be integrated (a bool counts as 0 or 1); the map has something
        to optimise."""
        waiting = int(waiting)
        catching_up = self.catch_up <= waiting < self.backlog
        self._catching_up = catching_up
        if waiting and (self.owed_s <= 0.0 or not can_step or catching_up):
            return Action.INTEGRATE
        if can_step:
            return Action.STEP
        return Action.WAIT

    def did_integrate(self, seconds: float) -> None:
        self.integrated += 1
        self.integrate_s += seconds
        if not self._catching_up:  # integrations that catch up owe nothing (else the debt would outlive the stream)
            self.owed_s += seconds * self.ratio

    def did_step(self, seconds: float) -> None:
        self.steps += 1
        self.step_s += seconds
        if self.owed_s > 0.0:  # a step that was owed: its overpayment is credit; free steps bank nothing
            self.owed_s -= seconds


class FusionStride:
    """Whether the frame integrated now fuses its depth into every fine lattice in view, or only into its new
    voxels': every frame while no other frame waits, else every `stride`-th frame (the frames in between still
    allocate voxels and fill the new ones' lattices, corner priors, colour prior and observed cells)."""

    def __init__(self, stride: int) -> None:
        if stride < 1:
            raise ConfigError(f"anytime.fine_prior_stride must be >= 1, got {stride}")
        self.stride = int(stride)
        self._since_all = 0  # frames integrated since the last one fused whole
        self.thinned = 0  # frames fused into their new voxels only

    def fuse_all(self, waiting: int) -> bool:
        """For the frame being integrated while `waiting` others wait."""
        self._since_all += 1
        if not waiting or self._since_all >= self.stride:
            self._since_all = 0
            return True
        self.thinned += 1
        return False


@dataclass
class Plateau:
    """The loss has stopped improving: the mean over each `window` steps is compared with the best mean so far;
    after `patience` windows in a row that are not below best * (1 - tol), the loss has plateaued. Losses of
    single steps are noisy (each samples other rays), their window means are not."""

    window: int = 50
    patience: int = 3
    tol: float = 0.005

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.best = math.inf
        self.flat_windows = 0
        self._sum = 0.0
        self._n = 0
        self.means: list[float] = []

    def add(self, loss: float) -> bool:
        """Take one step's loss; True once the loss has plateaued."""
        if math.isfinite(loss):
            self._sum += loss
            self._n += 1
        if self._n >= self.window:
            mean = self._sum / self._n
            self.means.append(mean)
            self._sum, self._n = 0.0, 0
            if mean < self.best * (1.0 - self.tol):
                self.best, self.flat_windows = mean, 0
            else:
                self.flat_windows += 1
        return self.settled

    @property
    def settled(self) -> bool:
        return self.flat_windows >= self.patience


def plateau_from(cfg: AnytimeConfig) -> Plateau:
    return Plateau(cfg.plateau_window, cfg.plateau_patience, cfg.plateau_tol)
