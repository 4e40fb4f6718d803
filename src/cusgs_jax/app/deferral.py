"""Which view the loop trains next when a program is late: the schedule of fresh and deferred batch positions.

The loop trains the batches ``batches(0) … batches(T − 1)`` (``T = train.iterations``), each exactly once. A
batch whose view needs more work capacity than the step has is replayed with grown capacities
(:mod:`cusgs_jax.training.capacity`); when the grown step's program is still compiling in the background, the
loop does not wait for it: the batch is *deferred* (:meth:`ViewQueue.defer`) and the loop trains the next
fresh one with the program it has. A deferred batch is trained as soon as its program is ready
(:meth:`ViewQueue.take_ready`, before any fresh batch), or, when no fresh batch is left or too many are
deferred, the loop waits for its program (:meth:`ViewQueue.must_wait`) — and says so.

Positions are plain ints and the queue knows nothing of JAX: what is deferred is a position and the work
capacities its replay needs (None: "try again with whatever the step has", after the anchor capacity changed).
A checkpoint keeps ``next`` and the deferred positions (:meth:`ViewQueue.as_dict`), so a resumed run trains
every batch once too.
"""

from __future__ import annotations

import dataclasses
import time

MAX_DEFERRED = 64  # deferred batches at most; one more and the loop waits for the oldest one's program
MAX_TRIES = 8  # fresh batches tried for one update before the loop waits (nearly every view overflowing)


@dataclasses.dataclass
class Deferred:
    """A batch position waiting for its program: the capacities its replay needs (None: any), the update count
    and the clock when it was deferred."""

    position: int
    capacities: object | None
    since_update: int
    since: float = dataclasses.field(default_factory=time.perf_counter)


@dataclasses.dataclass
class ViewQueue:
    """The batch positions still to train: the fresh ones from ``next`` to ``total`` and the deferred ones.

    Attributes:
      next: the next fresh position; total: ``train.iterations``.
      waiting: the deferred positions, oldest first.
      deferred / waits: batches deferred and waits for a late program (counted over the run, resumes included).
      steps_late / seconds_late: for every deferred batch trained, the updates and seconds between its
        deferral and its training (their max and sum are recorded).
      waited_s: seconds the loop stood still for a late program it could not train around.
    """

    next: int
    total: int
    waiting: list[Deferred] = dataclasses.field(default_factory=list)
    deferred: int = 0
    waits: int = 0
    waited_s: float = 0.0
    steps_late_max: int = 0
    steps_late_sum: int = 0
    seconds_late_max: float = 0.0
    trained_late: int = 0

    def fresh_left(self) -> bool:
        return self.next < self.total

    def take_fresh(self) -> int:
        """The next fresh position (consumed)."""
        position, self.next = self.next, self.next + 1
        return position

    def defer(self, position: int, capacities, updates: int) -> None:
        """Defer ``position`` until a step with ``capacities`` is ready (``updates``: updates done so far)."""
        self.waiting.append(Deferred(position, capacities, updates))
        self.deferred += 1

    def take_ready(self, is_ready) -> Deferred | None:
        """The oldest deferred batch whose capacities ``is_ready(capacities)`` says can run now (None: any
        capacities), removed from the queue; None if no deferred batch can run yet."""
        for index, item in enumerate(self.waiting):
            if item.capacities is None or is_ready(item.capacities):
                return self.waiting.pop(index)
        return None

    def capacities(self) -> list:
        """The capacities the deferred batches wait for (None ones left out)."""
        return [item.capacities for item in self.waiting if item.capacities is not None]

    def must_wait(self, tries: int) -> bool:
        """Whether the loop must wait for the oldest deferred batch's program rather than try another fresh one:
        no fresh batch is left, :data:`MAX_DEFERRED` are deferred, or ``tries`` fresh batches overflowed for this
        update (:data:`MAX_TRIES`: nearly every view overflows)."""
        return bool(self.waiting) and (not self.fresh_left() or len(self.waiting) >= MAX_DEFERRED
                                       or tries >= MAX_TRIES)

    def take_oldest(self) -> Deferred:
        return self.waiting.pop(0)

    def trained(self, item: Deferred, updates: int) -> None:
        """``item`` was trained at update ``updates``: how late it came."""
        late = updates - item.since_update
        self.trained_late += 1
        self.steps_late_max, self.steps_late_sum = max(self.steps_late_max, late), self.steps_late_sum + late
        self.seconds_late_max = max(self.seconds_late_max, time.perf_counter() - item.since)

    def waited(self, seconds: float) -> None:
        self.waits += 1
        self.waited_s += seconds

    def reset_capacities(self) -> None:
        """The anchor capacity changed: every deferred batch tries again with the step's new capacities."""
        for item in self.waiting:
            item.capacities = None

    def as_dict(self) -> dict:
        """A checkpoint's ``views`` and ``eval.json``'s ``deferred``: ``next``, the ``waiting`` positions, the
        counts and how late deferred batches came (updates: max and mean; seconds: max)."""
        return dict(next=self.next, waiting=[item.position for item in self.waiting], views=self.deferred,
                    waits=self.waits, waited_s=round(self.waited_s, 3), steps_late_max=self.steps_late_max,
                    steps_late_mean=round(self.steps_late_sum / self.trained_late, 2) if self.trained_late else 0.0,
                    seconds_late_max=round(self.seconds_late_max, 3), trained_late=self.trained_late,
                    steps_late_sum=self.steps_late_sum)

    def record(self) -> dict:
        """``eval.json``'s ``deferred``: views deferred, waits for a late program and their seconds, how late the
        deferred views were trained (updates: max and mean; seconds: max)."""
        saved = self.as_dict()
        return {key: saved[key] for key in ("views", "waits", "waited_s", "steps_late_max", "steps_late_mean",
                                            "seconds_late_max")}

    @classmethod
    def restored(cls, saved: dict | None, updates: int, total: int) -> ViewQueue:
        """The queue of a run resumed after ``updates`` updates from a checkpoint's ``views`` (None: written
        before deferral, every position below ``updates`` trained)."""
        if not saved:
            return cls(next=updates, total=total)
        queue = cls(next=int(saved["next"]), total=total, deferred=int(saved.get("views", 0)),
                    waits=int(saved.get("waits", 0)), waited_s=float(saved.get("waited_s", 0.0)),
                    steps_late_max=int(saved.get("steps_late_max", 0)),
                    steps_late_sum=int(saved.get("steps_late_sum", 0)),
                    seconds_late_max=float(saved.get("seconds_late_max", 0.0)),
                    trained_late=int(saved.get("trained_late", 0)))
        queue.waiting = [Deferred(int(position), None, updates) for position in saved.get("waiting", [])]
        return queue
