"""SerialRig's wait for an acquisition's frames (torchblur/hardware/serial_rig.py, ``_read_frames``;
docs/protocol.md, "Client rules"): a frame is declared lost when the controller is idle for two
consecutive ``STATUS?`` polls with no frame between them, not after two idle polls in all. Driven
over the emulator's real pseudo-terminal and camera channel, the frames held back on their way by
a slow link (:class:`LateFrames`) or dropped by the emulator (``fault.drop_frame``)."""
from __future__ import annotations

import time
from collections import deque

import pytest

from background import started_fleet, stop_fleet
from torchblur.hardware.errors import FrameTimeout
from torchblur.hardware.frames import Frame, FrameSource

POLL_S = 0.05  # the rig's silence before each STATUS? poll (s); short to keep the tests quick
N = 4  # frames per call


class LateFrames(FrameSource):
    """The emulator's camera behind a slow link: each acquisition's frames are all received from
    the emulator first (so its controller reports ``pending=0``, idle, before any is handed on),
    then frame ``i`` of the acquisition (0-based) is handed on only after ``holds[i]`` reads that
    time out (each one waits its full ``timeout_s``, s, as a silent link would).

    Args:
        inner: the emulator's :class:`~torchblur.hardware.frames.EmulatorFrames`.
        holds: ``{index in the acquisition: reads that time out before it}``.
    """

    def __init__(self, inner: FrameSource, holds: dict[int, int]):
        self.inner, self.holds = inner, dict(holds)
        self._queue: deque | None = None
        self._count, self._handed, self._held = 0, 0, 0

    @property
    def info(self):
        return self.inner.info

    def prepare(self, exposure_s: float, count: int) -> None:
        self.inner.prepare(exposure_s, count)

    def bind(self, first_counter: int, count: int) -> None:
        self.inner.bind(first_counter, count)
        self._queue, self._count, self._handed, self._held = None, count, 0, 0

    def read(self, timeout_s: float) -> Frame:
        if self._queue is None:  # the whole acquisition off the emulator: its controller is idle from now on
            self._queue = deque(self.inner.read(10.0) for _ in range(self._count))
        if not self._queue:
            return self.inner.read(timeout_s)
        if self._held < self.holds.get(self._handed, 0):
            self._held += 1
            time.sleep(timeout_s)
            raise FrameTimeout(f"no frame within {timeout_s:g} s (frame {self._handed} of the acquisition held back)")
        self._handed, self._held = self._handed + 1, 0
        return self._queue.popleft()

    def drain(self, quiet_s: float = 0.05) -> int:
        n = len(self._queue or ())
        self._queue = deque()
        return n + self.inner.drain(quiet_s)

    def reopen(self) -> None:
        self._queue = None
        self.inner.reopen()

    def close(self) -> None:
        self.inner.close()


def BACKGROUND_JOB(out, started):
    """Two emulators over real pseudo-terminals (40x40 frames, seed 1): a clean one, and one that
    never sends frame 3 (the last of the first call of N frames); started in the background as soon
    as the module is collected (tests/background.py), their start lines read -> ``{name: Emu}``."""
    from test_hardware_emulator import Emu

    return started_fleet({"clean": Emu(), "lost": Emu(f"fault.drop_frame={N - 1}")})


@pytest.fixture(scope="module")
def emulators(background, request):
    """The two emulators of :func:`BACKGROUND_JOB`."""
    emus = background.get(request.module.__name__)
    yield emus
    stop_fleet(emus)


def _open(emu, holds=None, **kw):
    from torchblur.hardware import SerialRig
    from torchblur.hardware.frames import EmulatorFrames

    frames = EmulatorFrames(emu.info["frames"])
    if holds is not None:
        frames = LateFrames(frames, holds)
    return SerialRig.open(emu.info["serial"], frames, timeout_s=2.0, poll_s=POLL_S, **kw)


def _never_arrived(rig) -> list[str]:
    return [e for e in rig.events if "never arrived" in e]


def test_frames_late_by_one_idle_poll_each_are_all_accepted(emulators):
    """Frames 1, 2 and 3 each come one poll timeout late while the controller is idle: three idle
    polls in the call, never two in a row without a frame, so nothing is lost and nothing retried."""
    with _open(emulators["clean"], {1: 1, 2: 1, 3: 1}) as rig:
        cap = rig.dark(n=N, exposure_s=0.01)
        assert not _never_arrived(rig) and rig.stats["retries"] == 0, rig.events
        c = cap.frame_counter.tolist()
        assert c == list(range(c[0], c[0] + N))
        assert cap.frames.shape == (N, 40, 40) and abs(float(cap.frames.mean()) - 100) < 1


def test_a_frame_late_by_two_consecutive_idle_polls_is_declared_lost(emulators):
    """Frames 0 and 1 arrive, then frame 2 is held back for two polls in a row of an idle controller:
    lost (FrameTimeout), in every attempt, although frames arrived before it."""
    from torchblur.hardware import AcquisitionStopped

    with _open(emulators["clean"], {2: 2}) as rig:
        first = rig.controller.status()["frames"]  # the counter of the first attempt's frame 0
        with pytest.raises(AcquisitionStopped, match="gave up after 3 attempt.*never arrived"):
            rig.dark(n=N, exposure_s=0.01)
        lost = _never_arrived(rig)
        assert [f"frame {first + N * k + 2} was triggered but never arrived" in e for k, e in enumerate(lost)] == [True] * 3, rig.events
        assert rig.stats["retries"] == 2
        assert all("idle for 2 polls in a row" in e for e in lost), lost


def test_the_idle_poll_count_is_the_rigs_and_its_message_says_it(emulators):
    """With ``idle_polls=3`` a frame held back for two idle polls in a row is accepted, one held
    back for three is lost, and the FrameTimeout says 3 polls (the count it waited, not a fixed 2)."""
    from torchblur.errors import InputTypeError, ParameterError
    from torchblur.hardware import AcquisitionStopped

    with _open(emulators["clean"], {2: 2}, idle_polls=3) as rig:
        rig.dark(n=N, exposure_s=0.01)
        assert not _never_arrived(rig) and rig.stats["retries"] == 0, rig.events
    with _open(emulators["clean"], {2: 3}, idle_polls=3, retries=0) as rig:
        with pytest.raises(AcquisitionStopped, match="never arrived"):
            rig.dark(n=N, exposure_s=0.01)
        lost = _never_arrived(rig)
        assert len(lost) == 1 and "idle for 3 polls in a row" in lost[0], rig.events
    with pytest.raises(ParameterError, match="idle_polls"):
        _open(emulators["clean"], idle_polls=0)
    with pytest.raises(InputTypeError, match="idle_polls"):
        _open(emulators["clean"], idle_polls=2.5)


def test_a_dropped_last_frame_is_still_declared_lost_and_the_call_redone(emulators):
    """The emulator never sends frame 3: frames 0-2 arrive, then the controller stays idle with no
    frame for two polls -> FrameTimeout, the call is redone and its frames are the redone ones."""
    with _open(emulators["lost"]) as rig:
        cap = rig.dark(n=N, exposure_s=0.01)
        lost = _never_arrived(rig)
        assert len(lost) == 1 and "frame 3 was triggered but never arrived" in lost[0], rig.events
        assert rig.stats["retries"] == 1
        assert cap.frame_counter.tolist() == list(range(N, 2 * N))  # the redone call's frames, not the first three
