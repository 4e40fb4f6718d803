"""CUS-GS feature-aware anchor pruning (docs/method.md#feature-aware-pruning).

Every anchor ``v`` gets a score

    S_v = λ_n ‖z_v‖ + λ_g g_v + S_v^contrib / mean_{alive u} S_u^contrib

and every pruning pass removes the ``floor(ratio · alive)`` alive anchors with
the lowest score. The pieces are pure and jittable; the configuration is a
frozen dataclass that callers close over (never traced):

* :class:`PruneStats` is accumulated inside the jitted train step by
  :func:`accumulate_prune_stats` (one call per rendered view);
* :func:`prune_pass` turns the statistics into cleared ``alive`` bits and
  resets them, so each pass only looks at the views since the previous one;
* :func:`prune_due` / :func:`stats_window` give the schedule.

Choices the paper leaves open (documented here, the place to change them):

* **Gradient term.** ``g_v`` is the *mean over the views since the last pass*
  of ``‖∇_{z_v} L‖`` (the gradient of that step's loss with respect to the
  anchor's latent, L2 norm over the F channels), over the views in which the
  anchor was decoded; 0 for an anchor not decoded since the last pass. We
  store Σ‖∇z L‖ and a count (not Σ‖∇z L‖²): a per-step norm is what the
  paper's formula writes, and the mean does not favour anchors that happen to
  be sampled more often. ``λ_n`` and ``λ_g`` multiply the raw ‖z‖ and g (the
  paper's 2 : 8); no normalisation is applied to those two terms.
* **Contribution term.** LightGaussian's global significance of a Gaussian is
  Σ over training views and composited pixels of ``opacity · T``, times
  ``(V / V_ref)^0.1``. Scale and opacity are view dependent here, so the
  volume weight is computed per view from that view's decoded Gaussians (only
  the active ones, opacity > 0) and applied before summing over views; an
  anchor's contribution is the sum over its N Gaussians. The raw sums are
  O(10²–10⁵) and grow with the number of views, so before they are added to
  the score they are divided by their mean over alive anchors (mean 0 → the
  term is 0). After normalisation the term is O(1), comparable to λ_n‖z‖.
* **V_ref.** LightGaussian (``calculate_v_imp_score``) sorts the volumes in
  *decreasing* order and takes the entry at index ``int(0.9 · G)``: despite the
  name "90th largest percentile" this is a *small* volume (about the 10th
  percentile in increasing order; 90 % of the Gaussians are at least as
  large). We reproduce exactly that: ``volume_percentile = p`` takes the entry
  at index ``floor(p/100 · G_active)`` (clamped to the last one) of the
  active volumes sorted in decreasing order. With power 0.1 the choice only
  rescales a view's weights by a common factor.
* **Candidates.** An anchor decoded in fewer than ``min_visits`` views since
  the last pass is not pruned (with ``min_visits = 1``, an anchor that just
  was not sampled — its contribution and gradient are 0 for lack of data, not
  because it is useless — is kept). The number removed is still computed from
  the alive count, capped by the number of candidates. ``min_visits = 0``
  makes every alive anchor a candidate.
* **Window.** Statistics are reset at every pass, so each pass sees the
  ``interval`` steps before it (:func:`stats_window` starts one interval
  before the first pass). LightGaussian sums over *all* training views; with
  one view per step a pass sees ``interval`` views.

Strategies (``prune.strategy``): ``"feature_aware"`` (this module, as
:class:`FeaturePruneStrategy`), ``"scaffold"`` and ``"none"``. Scaffold-GS's
opacity pruning lives in :class:`cusgs_jax.densify.scaffold.ScaffoldStrategy`
(it runs with growing, whatever the strategy here); for ``"scaffold"`` and
``"none"`` no feature-aware strategy is built at all, so nothing of this
module is traced or stored.

Naming (:mod:`cusgs_jax.types`): A anchor capacity, S gathered (visible) slots
per view, N Gaussians per anchor, F latent size, G = S·N Gaussians of a view
in slot order. V in the volume formulas (``V``, ``V_ref``) is LightGaussian's Gaussian volume,
not the table's V (views).
"""

from __future__ import annotations

import dataclasses
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np

from cusgs_jax.config import PruneConfig
from cusgs_jax.densify.base import Probe, Strategy, Tally, UpdateInfo
from cusgs_jax.model.anchors import AnchorState, PerAnchor

# Denominator bound of the exact-fraction path in :func:`_floor_ratio`: with
# q ≤ 46340 and p ≤ q, (count mod q) · p < q² < 2³¹ stays inside int32.
_MAX_DENOMINATOR = 46340


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PruneStats(PerAnchor):
    """Per-anchor statistics accumulated since the last pruning pass.

    Attributes:
      latent_grad_norm: [A] Σ over steps of ‖∇_{z_v} L‖ (steps where the
        anchor was decoded).
      grad_count: [A] number of those steps (views that decoded the anchor).
      contrib: [A] Σ over views of Σ_n significance_{v,n} · (V_{v,n}/V_ref)^power.
    """

    latent_grad_norm: jax.Array
    grad_count: jax.Array
    contrib: jax.Array

    @staticmethod
    def zeros(capacity: int) -> PruneStats:
        """All-zero statistics for ``capacity`` anchor slots (float32 [A] each)."""
        # three distinct buffers: a donated state must not hold one array twice
        return PruneStats(*(jnp.zeros(capacity, jnp.float32) for _ in range(3)))

    def clear(self, mask: jax.Array) -> PruneStats:
        """Zero the rows where ``mask`` [A] bool is set (e.g. slots refilled by growing)."""
        return jax.tree_util.tree_map(lambda x: jnp.where(mask, 0.0, x), self)


def _exact_fraction(ratio: float) -> tuple[int, int] | None:
    """``(p, q)`` with ``ratio`` the nearest double of p/q, q ≤ 46340 and 0 ≤ p ≤ q; None for other ratios."""
    frac = Fraction(float(ratio)).limit_denominator(_MAX_DENOMINATOR)
    p, q = frac.numerator, frac.denominator
    return (p, q) if float(frac) == float(ratio) and 0 <= p <= q else None


def _floor_fraction(count: jax.Array, p, q) -> jax.Array:
    """``floor(count · p / q)`` in int32 without overflow (q ≤ 46340, p ≤ q)."""
    return (count // q) * p + ((count % q) * p) // q


def _floor_ratio(count: jax.Array, ratio) -> jax.Array:
    """``floor(count · ratio)`` as int32, exact for fractional ``ratio``.

    A Python ``ratio`` that is a fraction p/q with q ≤ 46340 (every decimal
    like 0.001, 0.0015, 0.9 is) is evaluated in integer arithmetic, so e.g.
    ``floor(1000 · 0.01) = 10`` and ``floor(10 · 0.9) = 9`` whatever float32
    would round to. Other ratios (and traced ones) use float32
    ``floor(count · ratio)``.

    Args:
      count: [...] integer array (≥ 0).
    Returns:
      [...] int32.
    """
    count = jnp.asarray(count).astype(jnp.int32)
    if isinstance(ratio, (int, float)) and not isinstance(ratio, bool):
        exact = _exact_fraction(ratio)
        if exact is not None:  # the float *is* this fraction's nearest double
            return _floor_fraction(count, *exact)
    return jnp.floor(count.astype(jnp.float32) * jnp.asarray(ratio, jnp.float32)).astype(jnp.int32)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PruneDials:
    """The settings a pruning pass reads, as arrays (all [] shaped).

    A sweep over ``prune.ratio``, ``prune.lambda_norm``, ``prune.lambda_grad`` or ``prune.min_visits``
    changes these values, not the pass's program: :class:`FeaturePruneStrategy` passes them as
    arguments, so every job of such a sweep runs one compiled pass (shared through the persistent
    compilation cache). The pass computes what the constants gave: the same count
    ``floor(ratio · alive)`` (exact for decimal ratios, :func:`_floor_ratio`) and the same scores.

    Attributes:
      ratio: float32 ratio (used when it is no fraction p/q with q ≤ 46340).
      exact: bool, ``ratio`` is the fraction ``num / den``.
      num, den: int32 p and q (0 and 1 when not exact).
      lambda_norm, lambda_grad: float32 λ_n, λ_g.
      min_visits: float32, the views since the last pass an anchor needs to be a candidate.
    """

    ratio: jax.Array
    exact: jax.Array
    num: jax.Array
    den: jax.Array
    lambda_norm: jax.Array
    lambda_grad: jax.Array
    min_visits: jax.Array

    @staticmethod
    def of(cfg: PruneConfig) -> PruneDials:
        """The dials of ``cfg`` (host arrays)."""
        fraction = _exact_fraction(cfg.ratio)
        num, den = fraction if fraction is not None else (0, 1)
        return PruneDials(ratio=np.float32(cfg.ratio), exact=np.bool_(fraction is not None), num=np.int32(num),
                          den=np.int32(den), lambda_norm=np.float32(cfg.lambda_norm),
                          lambda_grad=np.float32(cfg.lambda_grad), min_visits=np.float32(cfg.min_visits))

    def count(self, alive_count: jax.Array) -> jax.Array:
        """``floor(ratio · alive_count)`` [] int32, as :func:`_floor_ratio` of the Python ratio."""
        count = jnp.asarray(alive_count).astype(jnp.int32)
        by_float = jnp.floor(count.astype(jnp.float32) * self.ratio).astype(jnp.int32)
        return jnp.where(self.exact, _floor_fraction(count, self.num, self.den), by_float)


def _order_key(values: jax.Array) -> jax.Array:
    """uint32 keys whose order is the float32 order of ``values`` (−0 before +0, NaN last)."""
    bits = jax.lax.bitcast_convert_type(values.astype(jnp.float32), jnp.uint32)
    negative = bits >> 31 == 1
    return jnp.where(negative, ~bits, bits | jnp.uint32(0x80000000))


def kth_smallest(values: jax.Array, k: jax.Array) -> jax.Array:
    """``jnp.sort(values)[k]`` without the sort: a bisection over the 32-bit order keys.

    32 counting passes over [G] (O(32·G), vectorised) instead of an O(G log G) sort,
    which XLA's CPU backend runs element by element (18 ms of a 320×240 step at 170k
    Gaussians). Exact: the result is an element of ``values``.

    Args:
      values: [G] float32; k: [] int32 in [0, G).
    Returns:
      [] float32, the k-th smallest entry (0-based; ties counted with multiplicity).
    """
    keys = _order_key(values)
    need = jnp.asarray(k, jnp.int32) + 1

    def halve(_, bounds):  # invariant: count(keys ≤ hi) ≥ need, and the answer lies in [lo, hi]
        lo, hi = bounds
        mid = lo + (hi - lo) // 2
        enough = jnp.sum(keys <= mid, dtype=jnp.int32) >= need
        return jnp.where(enough, lo, mid + 1), jnp.where(enough, mid, hi)

    bounds = (jnp.uint32(0), jnp.uint32(0xFFFFFFFF))
    _, key = jax.lax.fori_loop(0, 32, halve, bounds)
    return jnp.max(jnp.where(keys == key, values.astype(jnp.float32), -jnp.inf))  # the element itself


def gaussian_volume_weight(scales: jax.Array, active: jax.Array, cfg: PruneConfig = PruneConfig()) -> jax.Array:
    """LightGaussian's volume weight ``(V / V_ref)^power`` of one view's Gaussians.

    ``V = prod(scales)``; V_ref is the entry at index
    ``min(floor(volume_percentile/100 · G_active), G_active − 1)`` of the
    active volumes sorted in decreasing order (LightGaussian
    ``calculate_v_imp_score``; 90 → a small, ~10th-percentile volume). Not
    differentiated (statistics only).

    Args:
      scales: [G, 3] linear standard deviations.
      active: [G] bool; inactive Gaussians neither enter V_ref nor get a weight.
    Returns:
      [G] float32, 0 where inactive (and where the view has no active
      Gaussian); a non-positive V_ref is replaced by 1.
    """
    scales = jax.lax.stop_gradient(scales).astype(jnp.float32)
    volume = jnp.prod(scales, axis=-1)
    n = jnp.sum(active).astype(jnp.int32)
    k_desc = jnp.minimum(_floor_ratio(n, cfg.volume_percentile / 100.0), n - 1)
    # the n active volumes come first in increasing order; V_ref is entry n − 1 − k_desc
    v_ref = kth_smallest(jnp.where(active, volume, jnp.inf), jnp.clip(n - 1 - k_desc, 0, volume.shape[0] - 1))
    v_ref = jnp.where((n > 0) & (v_ref > 0) & jnp.isfinite(v_ref), v_ref, 1.0)
    ratio = jnp.where(active, volume / v_ref, 0.0)
    return jnp.where(active, ratio ** cfg.volume_power, 0.0)


def accumulate_prune_stats(stats: PruneStats, slots: jax.Array, valid: jax.Array, latent_grad: jax.Array,
                           significance: jax.Array, scales: jax.Array, active: jax.Array, enabled: jax.Array,
                           cfg: PruneConfig = PruneConfig()) -> PruneStats:
    """Add one view's pruning statistics into the anchor slots (pure, jittable).

    Inputs are in the gathered order of ``model.decode.decode_view``: Gaussian
    ``i`` belongs to gathered slot ``i // N``.

    Args:
      stats: [A] statistics so far.
      slots: [S] int32 anchor slot of each gathered entry.
      valid: [S] bool, entry holds a decoded anchor (padding entries may
        repeat a slot; they are ignored).
      latent_grad: [S, F] ∂L/∂z of the gathered latents (equivalently
        ``grads["anchor"].latent[slots]``).
      significance: [S·N] ``RenderOutput.significance`` (Σ opacity·T).
      scales: [S·N, 3] decoded scales of the view.
      active: [S·N] bool, Gaussians switched on (``Gaussians.active``).
      enabled: [] bool, e.g. ``stats_window(step) & finite``.
      cfg: closed over (volume power and percentile).
    Returns:
      Updated :class:`PruneStats`. Invalid entries, inactive Gaussians and a
      disabled call add exactly 0 (``jnp.where``, so NaN/inf there cannot leak).
    """
    capacity = stats.contrib.shape[0]
    num_slots = slots.shape[0]
    n = significance.shape[0] // num_slots
    on = valid & jnp.asarray(enabled, bool)  # [S]
    gaussian_on = active & jnp.repeat(valid, n)  # [S·N]
    weight = gaussian_volume_weight(scales, gaussian_on, cfg)
    sig = jax.lax.stop_gradient(significance).astype(jnp.float32)
    per_gaussian = jnp.where(gaussian_on, sig * weight, 0.0)
    per_anchor = jnp.where(on, jnp.sum(per_gaussian.reshape(num_slots, n), axis=-1), 0.0)
    grad = jax.lax.stop_gradient(latent_grad).astype(jnp.float32)
    grad_norm = jnp.where(on, jnp.sqrt(jnp.sum(jnp.where(on[:, None], grad, 0.0) ** 2, axis=-1)), 0.0)
    index = jnp.where(on, slots, capacity)  # out of range → dropped
    def add(acc, x):
        return acc.at[index].add(x, mode="drop")

    return PruneStats(
        latent_grad_norm=add(stats.latent_grad_norm, grad_norm),
        grad_count=add(stats.grad_count, on.astype(jnp.float32)),
        contrib=add(stats.contrib, per_anchor),
    )


def anchor_scores(latent: jax.Array, stats: PruneStats, alive: jax.Array,
                  cfg: PruneConfig | PruneDials = PruneConfig()) -> jax.Array:
    """Feature-aware pruning score of every anchor slot.

    ``S_v = λ_n ‖z_v‖ + λ_g g_v + contrib_v / mean_{alive} contrib`` with
    ``g_v = latent_grad_norm_v / grad_count_v`` (0 when never seen) and the
    contribution term 0 when the alive mean is 0.

    Args:
      latent: [A, F] anchor latents z.
      stats: accumulated :class:`PruneStats`.
      alive: [A] bool.
      cfg: where ``lambda_norm`` and ``lambda_grad`` come from (a :class:`PruneDials` traces them).
    Returns:
      [A] float32; +inf for dead slots (never chosen).
    """
    latent = jax.lax.stop_gradient(latent).astype(jnp.float32)
    norm = jnp.sqrt(jnp.sum(latent ** 2, axis=-1))
    count = stats.grad_count
    grad = jnp.where(count > 0, stats.latent_grad_norm / jnp.maximum(count, 1.0), 0.0)
    alive_count = jnp.sum(alive).astype(jnp.float32)
    mean_contrib = jnp.sum(jnp.where(alive, stats.contrib, 0.0)) / jnp.maximum(alive_count, 1.0)
    contrib = jnp.where(mean_contrib > 0, stats.contrib / jnp.where(mean_contrib > 0, mean_contrib, 1.0), 0.0)
    score = cfg.lambda_norm * norm + cfg.lambda_grad * grad + contrib
    return jnp.where(alive, score, jnp.inf)


def select_prune(scores: jax.Array, alive: jax.Array, ratio, eligible: jax.Array | None = None) -> jax.Array:
    """The ``floor(ratio · alive_count)`` lowest-scoring alive anchors.

    Static shapes: one lexicographic sort of (not candidate, score, index) and
    a rank mask; jittable with a traced ``alive``. Ties are broken by the
    lower index; NaN scores sort after every number. Dead slots are never
    selected, whatever their score.

    Args:
      scores: [A].
      alive: [A] bool; the count ``floor(ratio · Σ alive)`` is taken from it
        (exact integer arithmetic for decimal Python ratios, see
        :func:`_floor_ratio`).
      ratio: Python float (or a traced scalar, then float32 arithmetic).
      eligible: [A] bool or None; when given only ``alive & eligible``
        anchors are candidates (at most that many are selected).
    Returns:
      [A] bool, ``min(floor(ratio · alive_count), candidates)`` entries set.
    """
    candidate = alive if eligible is None else alive & eligible
    return _lowest(scores, candidate, _floor_ratio(jnp.sum(alive), ratio))


def _lowest(scores: jax.Array, candidate: jax.Array, k: jax.Array) -> jax.Array:
    """[A] bool: the ``k`` lowest-scoring ``candidate`` slots (ties: the lower index; NaN last)."""
    num = scores.shape[0]
    index = jnp.arange(num, dtype=jnp.int32)
    *_, order = jax.lax.sort(((~candidate).astype(jnp.int32), scores, index), num_keys=3)
    rank = jnp.zeros(num, jnp.int32).at[order].set(index)
    return (rank < k) & candidate


def prune_pass(anchors: AnchorState, stats: PruneStats, cfg: PruneConfig = PruneConfig(),
               dials: PruneDials | None = None) -> tuple[AnchorState, PruneStats, dict[str, jax.Array]]:
    """One feature-aware pruning pass (pure, jittable; ``cfg`` closed over).

    Args:
      anchors: the anchors (centres, alive, latents z [A, F]).
      stats: statistics accumulated since the last pass.
      dials: the ratio, weights and ``min_visits`` as arrays (traced when passed to a jitted pass);
        None: those of ``cfg``. The result is the same either way.
    Returns:
      (anchors with the selected ``alive`` bits cleared, statistics reset to
      zero for every slot, info) with info ``{"pruned", "alive",
      "candidates"}`` int32 scalars. For strategies "scaffold" and "none" the
      anchors are returned unchanged, the statistics are still reset.
    """
    fresh = PruneStats.zeros(anchors.capacity)
    alive = anchors.alive
    if cfg.strategy != "feature_aware":
        zero = jnp.int32(0)
        return anchors, fresh, dict(pruned=zero, alive=jnp.sum(alive).astype(jnp.int32), candidates=zero)
    dials = PruneDials.of(cfg) if dials is None else dials
    scores = anchor_scores(anchors.params.latent, stats, alive, dials)
    eligible = stats.grad_count >= dials.min_visits
    prune = _lowest(scores, alive & eligible, dials.count(jnp.sum(alive)))
    new_alive = alive & ~prune
    info = dict(pruned=jnp.sum(prune).astype(jnp.int32), alive=jnp.sum(new_alive).astype(jnp.int32),
                candidates=jnp.sum(alive & eligible).astype(jnp.int32))
    return anchors.replace(alive=new_alive), fresh, info


def prune_due(step, cfg: PruneConfig = PruneConfig()):
    """Whether a pass runs at ``step``: ``start ≤ step ≤ stop`` and ``step % interval == 0``.

    Works on Python ints (returns bool) and traced int arrays (returns [] bool).
    Always False for strategies other than "feature_aware".
    """
    if cfg.strategy != "feature_aware":
        return False if isinstance(step, int) else jnp.zeros((), bool)
    due = (step >= cfg.start) & (step <= cfg.stop) & (step % cfg.interval == 0)
    return bool(due) if isinstance(step, int) else due


def stats_window(step, cfg: PruneConfig = PruneConfig()):
    """Whether statistics are accumulated at ``step``: ``start − interval ≤ step < stop``.

    So the first pass, like every later one, sees ``interval`` steps. Python
    int → bool, traced → [] bool; always False for other strategies.
    """
    if cfg.strategy != "feature_aware":
        return False if isinstance(step, int) else jnp.zeros((), bool)
    on = (step >= cfg.start - cfg.interval) & (step < cfg.stop)
    return bool(on) if isinstance(step, int) else on


class FeaturePruneStrategy(Strategy):
    """CUS-GS feature-aware pruning as a densification strategy (see :mod:`cusgs_jax.densify`).

    State: :class:`PruneStats`, accumulated inside the jitted step
    (:meth:`accumulate`); every due step :meth:`update` runs the jitted
    :func:`prune_pass` (a mask: no shape changes, nothing recompiles). Before the first
    pass it measures the render time of the unpruned model (:meth:`before_first_update`); it
    reports ``pruned`` in every ``metrics.jsonl`` row and ``render_ms_before_prune`` and the
    ``prune`` block's ``passes`` / ``pruned`` in ``eval.json``.
    """

    name = "feature_prune"

    def __init__(self, cfg: PruneConfig):
        self.cfg = cfg
        self.dials = PruneDials.of(cfg)  # arguments, not constants: a sweep over them shares the program

        def pruning_pass(anchors, stats, dials):  # its name in compile logs: jit(pruning_pass)
            return prune_pass(anchors, stats, cfg, dials)

        self._pass = jax.jit(pruning_pass, donate_argnums=(0, 1))

    def init_state(self, capacity: int) -> PruneStats:
        return PruneStats.zeros(capacity)

    def accumulate(self, stats: PruneStats, view) -> PruneStats:
        """Inside the step: add one view's ‖∇_z L‖ and LightGaussian contribution."""
        enabled = stats_window(view.step, self.cfg) & view.finite
        return accumulate_prune_stats(stats, view.slots.slots, view.slots.valid, view.latent_grad,
                                      view.render.significance, view.gaussians.scales, view.gaussians.active,
                                      enabled, self.cfg)

    def due(self, step: int) -> bool:
        """A pass after ``step`` completed steps."""
        return prune_due(step, self.cfg)

    def only_removes(self, step: int) -> bool:
        """A pruning pass only clears ``alive`` bits."""
        del step
        return True

    def before_first_update(self, probe: Probe) -> dict:
        """The held-out render time per view of the model before any pass: ``render_ms_before_prune``."""
        return dict(render_ms_before_prune=probe.render_ms_per_view())

    def update(self, state, tx, step: int) -> tuple[object, UpdateInfo]:
        """Host side, after step ``step``: one pruning pass.

        Returns:
          (state, :class:`~cusgs_jax.densify.base.UpdateInfo`) with ``pruned`` and ``extra``
          ``alive`` (anchors after the pass) and ``candidates`` (alive anchors seen often enough).
        """
        del tx, step  # a mask flip: shapes, moments and the other statistics are untouched
        anchors, stats, info = self._pass(state.anchors, state.densify[self.name], self.dials)
        info = jax.device_get(info)
        return (state.replace(anchors=anchors, densify={**state.densify, self.name: stats}),
                UpdateInfo(pruned=int(info["pruned"]),
                           extra=dict(alive=int(info["alive"]), candidates=int(info["candidates"]))))

    def log_values(self, tally: Tally) -> dict:
        """``pruned``: anchors removed by the passes so far."""
        return dict(pruned=tally.pruned)

    def results(self, tally: Tally) -> dict:
        """``render_ms_before_prune`` and the ``prune`` block's ``passes`` and ``pruned``."""
        return dict(render_ms_before_prune=tally.values.get("render_ms_before_prune"),
                    prune=dict(passes=tally.updates, pruned=tally.pruned))
