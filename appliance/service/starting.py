"""Start-up progress: what the monitor is doing before its first map, as lines and in the live view.

A first start builds the reconstruction model and may calibrate the virtual mat, which takes a while; until
the first frame the nurse's screen would otherwise say only that no frame was written. Each phase is published
through the same live channel as the frames (``{"starting": {"phase": ..., "share": ...}}``), so the screen
reads one file for both, and the first frame's snapshot replaces it. A start-up that fails says so at once
(``"failed": true``), so the screen sounds its alarm rather than show the last step as under way.
"""

from __future__ import annotations

from collections.abc import Callable

from appliance.service.live import LiveChannel

PHASES = {"model": ("building the reconstruction model", 0.0, 0.8),
          "calibration": ("taking the pressure calibration", 0.8, 0.95),
          "reference": ("resuming or taking the empty-mat reference", 0.95, 1.0)}
"""Each phase's words and the part of the whole start-up it spans: the model build is most of a first start."""


class StartingReport:
    """Publishes each start-up step as a share of the whole start-up; the shares only rise."""

    def __init__(self, live: LiveChannel | None, say: Callable[[str], None]):
        self.live, self.say = live, say
        self.share = 0.0
        self.phase, self.step = PHASES["model"][0], ""

    def __call__(self, phase: str, share_of_phase: float, step: str = "") -> None:
        """Say ``step`` of ``phase`` (a key of :data:`PHASES`) and publish how far the start-up is."""
        if phase not in PHASES:
            raise ValueError(f"unknown start-up phase {phase!r}: one of {', '.join(PHASES)}")
        if not 0.0 <= share_of_phase <= 1.0:
            raise ValueError(f"the share of a start-up phase is from 0 to 1, got {share_of_phase!r}")
        words, start, end = PHASES[phase]
        self.share = max(self.share, round(start + share_of_phase * (end - start), 3))
        self.say(f"{words}: {step} ({share_of_phase:.0%})" if step else f"{words} ({share_of_phase:.0%})")
        self.phase, self.step = words, step
        if self.live is not None:
            self.live.publish({"starting": {"phase": words, "step": step, "share": self.share}})

    def failed(self) -> None:
        """Publish that the start-up stopped at its last step (the reason goes to the log, not the screen)."""
        if self.live is not None:
            self.live.publish({"starting": {"phase": self.phase, "step": self.step, "share": self.share,
                                            "failed": True}})
