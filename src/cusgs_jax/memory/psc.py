"""Principal Scene Components (PSC): M3's greedy reduction of a model's feature vectors.

Given all views' feature vectors of one foundation model, flattened to rows
``[M, D]``, the PSC bank is built by one ordered scan: all-zero rows ("no target")
are skipped; row ``r`` is kept iff its cosine to EVERY entry kept so far is
strictly below ``gamma``. The bank stores the ORIGINAL (unnormalised) vectors.

What "the cosine" is, exactly
-----------------------------
Every row is first cast to float32 (the bank's dtype); non-finite values are an
error. The decision uses :func:`exact_cosine` of the two float32 rows ``a, b``::

    cos(a, b) = <a, b> / sqrt(<a, a> <b, b>)

where each dot product is the correctly rounded float64 value of the exact sum
(products of float32 numbers are exact in float64; ``math.fsum`` sums them
exactly), followed by three correctly rounded float64 operations. It is a pure
function of the two rows -- independent of summation order, BLAS, backend and
chunking -- and equal rows (or rows that differ by a power-of-two factor) have a
cosine of exactly 1.0.

Why not "float32 cosines from a matmul" for the decision: two float32 dot
products of the same vectors computed in a different order (NumPy vs XLA, CPU
vs GPU, a Gram block vs a bank block) may differ in the last bit, which flips a
decision whenever a cosine sits at ``gamma`` -- and with ``gamma = 1.0``
duplicated feature vectors sit there by construction. So the fast path computes
cosines in float32 (NumPy matmuls, BLAS, in any summation order) only to
*screen*: with ``tol`` a rigorous bound on ``|float32 cosine - exact cosine|``
(float32 normalisation plus any-order float32 summation, :func:`screen_tolerance`),
a float32 cosine below ``gamma - tol`` proves "below", one at or above
``gamma + tol`` proves "at or above", and only the pairs in between are decided by
:func:`exact_cosine`. :func:`build` is therefore exactly equal to the plain
:func:`~cusgs_jax.testing.psc_reference.build_reference` (same kept rows, in the same order).

``gamma`` semantics. Ties (cosine exactly ``gamma``) are rejected. With
``gamma = 1.0`` (M3's setting for SEEM and LLaMA3) only rows with exactly the same
direction as a kept entry are rejected -- repeats and power-of-two multiples,
whose cosine is exactly 1.0 -- and every other non-zero row is kept,
i.e. "keep all distinct". A row scaled by a factor like 3 is not exactly parallel
after float32 rounding; its cosine may round to 1.0 (rejected) or fall just below
(kept). ``gamma > 1`` keeps every non-zero row.

Cost. Rows are processed in chunks of ``chunk``: (1) each chunk row's maximum
float32 cosine to the bank, by BLAS matmuls over bank blocks (memory
``chunk x block``, never ``chunk x M``); (2) the surviving candidates' float32 Gram
matrix and a short sequential pass (a candidate depends only on earlier kept
candidates of the chunk, and rows with no near-or-above-threshold earlier
candidate are kept without looking). The bank lives in preallocated host buffers
whose capacity doubles, so appending is amortised O(1) per row. Near-threshold
pairs are decided exactly in vectorised batches (``math.fsum`` per pair); only data
with very many near-parallel but not equal rows at ``gamma = 1.0`` spends
noticeable time there.

All of it is NumPy on the host, on purpose: the scan is a sequence of small,
data-dependent steps, and as device work each would be a kernel launch, a
transfer and a sync (and a compile per shape) — on a GPU machine that made the
demo's build 6.5× slower than on a 2-core CPU (docs/scaling.md#on-a-gpu).
"""

from __future__ import annotations

import dataclasses
import math
import types
from collections.abc import Mapping

import numpy as np

__all__ = [
    "M3_GAMMAS",
    "PSCBank",
    "build",
    "build_per_model",
    "exact_cosine",
    "screen_tolerance",
]

#: M3's PSC thresholds per foundation model (cosine, strict ``<`` keeps a row).
M3_GAMMAS: Mapping[str, float] = types.MappingProxyType({
    "clip": 0.80,
    "siglip": 0.85,
    "dinov2": 0.75,
    "seem": 1.0,
    "llama3": 1.0,
    "llamav": 0.60,
})

_SCREEN_ELEMENTS = 1 << 24  # chunk x bank-block float32 similarities per screening matmul (64 MiB)


@dataclasses.dataclass(frozen=True, eq=False)
class PSCBank:
    """A model's memory bank of principal scene components.

    Attributes:
      entries: [M, D] float32, the kept rows, original (unnormalised), in scan order.
      count: M, the number of entries.
      gamma: the cosine threshold the bank was built with.
      indices: [M] int64, each entry's row in the flattened input ``features.reshape(-1, D)``
        (empty when unknown, e.g. a bank constructed by hand).
      truncated: True when ``max_entries`` stopped the scan while a further row would
        have been kept.
    """

    entries: np.ndarray
    count: int
    gamma: float
    indices: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    truncated: bool = False

    def __post_init__(self):
        if self.entries.ndim != 2 or self.entries.dtype != np.float32:
            raise ValueError(f"entries must be [M, D] float32, got {self.entries.shape} {self.entries.dtype}")
        if self.count != self.entries.shape[0]:
            raise ValueError(f"count {self.count} != len(entries) {self.entries.shape[0]}")
        if self.indices.size and self.indices.shape != (self.count,):
            raise ValueError(f"indices must be [{self.count}], got {self.indices.shape}")

    @property
    def dim(self) -> int:
        """D, the feature dimension."""
        return int(self.entries.shape[1])


# --------------------------------------------------------------------------- the definition


def exact_cosine(a: np.ndarray, b: np.ndarray) -> float:
    """The PSC decision cosine of two non-zero float32 rows ``a, b`` [D] (a Python float).

    ``<a,b> / sqrt(<a,a> <b,b>)`` with every dot product the correctly rounded float64
    value of the exact sum, then correctly rounded float64 multiply, sqrt and divide, so
    the result depends on nothing but the two rows. Equal rows (elementwise ``==``, so
    ``-0.0 == 0.0``) give exactly 1.0: short-cut here, and the formula agrees, since
    ``sqrt(x*x) == x`` in binary floating point without over/underflow (which the float32
    range cannot cause in float64); rows differing by a power-of-two factor give 1.0 too.
    """
    return _exact_cos(np.asarray(a, np.float32), np.asarray(b, np.float32))


def _exact_cos(a: np.ndarray, b: np.ndarray) -> float:
    """:func:`exact_cosine` of two float32 [D] arrays, without argument conversion."""
    if np.array_equal(a, b):
        return 1.0
    a64 = a.astype(np.float64)
    b64 = b.astype(np.float64)
    ab = math.fsum((a64 * b64).tolist())
    aa = math.fsum((a64 * a64).tolist())
    bb = math.fsum((b64 * b64).tolist())
    return ab / math.sqrt(aa * bb)


def _exact_dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise <a_k, b_k> of float32 [k, D] arrays: [k] float64, each correctly rounded.

    The same values as the ``math.fsum`` dot products of :func:`_exact_cos` (products of
    float32 numbers are exact in float64; fsum rounds their exact sum once).
    """
    k, dim = a.shape
    out = np.empty(k, np.float64)
    step = max(1, (1 << 20) // max(dim, 1))
    for s0 in range(0, k, step):
        prods = a[s0:s0 + step].astype(np.float64) * b[s0:s0 + step].astype(np.float64)
        out[s0:s0 + step] = list(map(math.fsum, prods.tolist()))
    return out


def _cached_sq(rows: np.ndarray, cache: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Exact squared norms <r, r> of rows[idx] [k]; fills NaN slots of ``cache`` on first use."""
    todo = np.unique(idx[np.isnan(cache[idx])])
    if todo.size:
        cache[todo] = _exact_dots(rows[todo], rows[todo])
    return cache[idx]


def _pairs_at_least(a_rows, a_sq, ai, b_rows, b_sq, bj, gamma) -> np.ndarray:
    """[k] bool: ``_exact_cos(a_rows[ai[k]], b_rows[bj[k]]) >= gamma``, bit for bit.

    a_rows, b_rows: float32 [*, D]; ai, bj [k] row indices; a_sq, b_sq: NaN-initialised
    caches of the rows' exact squared norms (filled only where needed). NumPy's float64
    multiply, sqrt and divide are IEEE correctly rounded like ``math``'s, so the cosines
    equal _exact_cos's.
    """
    a, b = a_rows[ai], b_rows[bj]
    equal = np.all(a == b, axis=1)
    hit = equal & (1.0 >= gamma)  # _exact_cos returns exactly 1.0 for value-equal rows
    rest = np.flatnonzero(~equal)
    if rest.size:
        norms = _cached_sq(a_rows, a_sq, ai[rest]) * _cached_sq(b_rows, b_sq, bj[rest])
        hit[rest] = _exact_dots(a[rest], b[rest]) / np.sqrt(norms) >= gamma
    return hit


def screen_tolerance(dim: int) -> float:
    """Bound on ``|float32 cosine - exact_cosine|`` for D = ``dim``, with a 2x margin.

    The float32 cosine is ``<u, v>`` of the float32 unit copies ``u = f32(a / |a|_f64)``
    summed in float32 in any order (FMA, blocking and flush-to-zero allowed). Terms:
    normalisation (each ``u_i`` within a relative ``2^-24 + (D+3) 2^-53`` of the exact
    unit vector: ``2^-23 + (D+3) 2^-52`` on the dot product), float32 summation
    (``gamma_D = D 2^-24 / (1 - D 2^-24)`` times ``sum |u_i v_i| <= 1 + 2^-22``),
    flushed subnormals (``D 2^-123``) and the float64 rounding of :func:`exact_cosine`
    (``2^-50``).
    """
    d = float(dim)
    u = 2.0 ** -24
    gamma_d = d * u / (1.0 - d * u)
    bound = 2.0 ** -23 + (d + 3) * 2.0 ** -52 + gamma_d * (1 + 2.0 ** -21) + d * 2.0 ** -123 + 2.0 ** -50
    return 2.0 * bound


def _as_rows(features) -> np.ndarray:
    """features [..., D] (NumPy/JAX, any float dtype) as a [M, D] NumPy view."""
    x = np.asarray(features)
    if x.ndim < 2:
        raise ValueError(f"features must be [..., D] with at least 2 dims, got shape {x.shape}")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise TypeError(f"features must be numeric, got {x.dtype}")
    return x.reshape(-1, x.shape[-1])


def _rows_f32(x: np.ndarray) -> np.ndarray:
    """Rows cast to float32; non-finite values (including float32 overflow) raise."""
    with np.errstate(over="ignore"):  # overflow to inf is reported below
        x32 = np.ascontiguousarray(x, dtype=np.float32)
    if not np.all(np.isfinite(x32)):
        raise ValueError("features contain non-finite values (after the cast to float32)")
    return x32


def _unit(x32: np.ndarray) -> np.ndarray:
    """[n, D] float32 non-zero rows -> float32 unit copies, normalised in float64."""
    x64 = x32.astype(np.float64)
    norm = np.sqrt(np.einsum("nd,nd->n", x64, x64))
    return (x64 / norm[:, None]).astype(np.float32)


def _validate(gamma, chunk, max_entries):
    gamma = float(gamma)
    if math.isnan(gamma):
        raise ValueError("gamma is NaN")
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if max_entries is not None and int(max_entries) < 0:
        raise ValueError(f"max_entries must be >= 0 or None, got {max_entries}")
    return gamma, int(chunk), None if max_entries is None else int(max_entries)


# --------------------------------------------------------------------------- fast build


class _Bank:
    """Growable bank buffers: original rows, unit rows, source indices (host arrays)."""

    def __init__(self, dim: int, capacity: int, chunk: int):
        self.dim, self.chunk, self.count = dim, chunk, 0
        cap = 1 << max(0, int(capacity) - 1).bit_length()  # a power of two
        self._block = max(64, _SCREEN_ELEMENTS // chunk)  # bank rows per screening matmul
        self.rows = np.empty((cap, dim), np.float32)
        self.units = np.empty((cap, dim), np.float32)
        self.indices = np.empty(cap, np.int64)
        self.sq = np.full(cap, np.nan)  # exact squared norms, computed on first use

    @property
    def capacity(self) -> int:
        return self.rows.shape[0]

    def _grow(self, needed: int):
        cap = self.capacity
        while cap < needed:
            cap *= 2
        if cap == self.capacity:
            return
        n = self.count
        for name in ("rows", "units", "indices", "sq"):
            old = getattr(self, name)
            new = np.full((cap,) + old.shape[1:], np.nan) if name == "sq" else np.empty(
                (cap,) + old.shape[1:], old.dtype)
            new[:n] = old[:n]
            setattr(self, name, new)

    def max_cosine(self, units: np.ndarray) -> np.ndarray:
        """[n, D] unit rows (n <= chunk) -> [n] max float32 cosine to the bank (-inf when it is empty)."""
        best = np.full(len(units), -np.inf, np.float32)
        for start in range(0, self.count, self._block):
            sims = units @ self.units[start:min(self.count, start + self._block)].T  # float32, any order
            np.maximum(best, sims.max(axis=1), out=best)
        return best

    def append(self, rows: np.ndarray, units: np.ndarray, indices: np.ndarray):
        k = len(rows)
        if k == 0:
            return
        self._grow(self.count + k)
        n = self.count
        self.rows[n:n + k] = rows
        self.units[n:n + k] = units
        self.indices[n:n + k] = indices
        self.count = n + k


def _rejected_by_bank(bank: _Bank, rows, units, gamma, lo, hi) -> np.ndarray:
    """[n] bool: row has exact cosine >= gamma to some bank entry. rows/units [n, D]."""
    n = len(rows)
    if bank.count == 0 or n == 0:
        return np.zeros(n, bool)
    best = bank.max_cosine(units)
    rejected = best >= hi
    ambiguous = np.flatnonzero((best >= lo) & ~rejected)
    if ambiguous.size == 0:
        return rejected
    count = bank.count
    row_sq = np.full(n, np.nan)
    step = max(1, (1 << 22) // count)
    for s0 in range(0, ambiguous.size, step):
        sel = ambiguous[s0:s0 + step]
        sims = units[sel] @ bank.units[:count].T  # float32, any order: same bound as the device
        decided = np.any(sims >= hi, axis=1)
        # The rest: decide every (row, entry) pair whose float32 cosine is in [lo, hi) exactly.
        pi, pj = np.nonzero((sims >= lo) & ~decided[:, None])
        if pi.size:
            ri = sel[pi]
            hit = _pairs_at_least(rows, row_sq, ri, bank.rows, bank.sq, pj, gamma)
            decided[pi[hit]] = True
        rejected[sel] = decided
    return rejected


def _greedy_within(rows, units, gamma, lo, hi) -> np.ndarray:
    """[n] bool: kept by the greedy scan of these candidates among themselves (in order)."""
    n = len(rows)
    if n <= 1:
        return np.ones(n, bool)
    gram = units @ units.T  # [n, n] float32
    deps = np.tril(gram >= lo, -1)
    has_dep = deps.any(axis=1)
    kept = ~has_dep  # a row with no near-or-above earlier candidate is kept regardless
    sq = np.full(n, np.nan)
    for i in np.flatnonzero(has_dep):  # increasing: kept[:i] is final when row i is decided
        js = np.flatnonzero(deps[i, :i] & kept[:i])
        if js.size == 0:
            kept[i] = True
        elif np.any(gram[i, js] >= hi):
            kept[i] = False
        else:
            kept[i] = not np.any(_pairs_at_least(rows, sq, np.full(js.size, i), rows, sq, js, gamma))
    return kept


def build(features, gamma: float, *, chunk: int = 4096, max_entries: int | None = None,
          initial_capacity: int | None = None) -> PSCBank:
    """Build a PSC bank: exactly the plain scan of :mod:`cusgs_jax.testing.psc_reference`, chunked and fast.

    Args:
      features: [..., D] feature vectors of one model (all views, flattened to [M, D] in
        C order), NumPy or JAX, any float dtype; rows are cast to float32 chunk by chunk.
        All-zero rows mean "no target" and are skipped.
      gamma: cosine threshold (keep iff cosine to every kept entry < gamma; see the
        module docstring for the exact cosine and for gamma = 1.0).
      chunk: rows per chunk (memory ~ chunk^2 + chunk x 4096 float32 per step).
      max_entries: optional cap on M; the scan stops (``truncated=True``) when a row
        would become entry number ``max_entries + 1``.
      initial_capacity: initial bank buffer rows (rounded up to a power of two);
        the buffer doubles as needed. Default ``2 * chunk``.
    Returns:
      PSCBank(entries [M, D] float32, count M, gamma, indices [M], truncated).
    """
    gamma, chunk, max_entries = _validate(gamma, chunk, max_entries)
    x = _as_rows(features)
    m, dim = x.shape
    tol = screen_tolerance(dim)
    lo, hi = gamma - tol, gamma + tol
    bank = _Bank(dim, initial_capacity or 2 * chunk, chunk)
    truncated = False
    for start in range(0, m, chunk):
        xc = _rows_f32(x[start:start + chunk])
        nz = np.flatnonzero(np.any(xc != 0, axis=1))
        if nz.size == 0:
            continue
        rows = xc[nz]
        units = _unit(rows)
        alive = ~_rejected_by_bank(bank, rows, units, gamma, lo, hi)
        cand = np.flatnonzero(alive)
        kept = cand[_greedy_within(rows[cand], units[cand], gamma, lo, hi)]
        if max_entries is not None and bank.count + kept.size > max_entries:
            kept = kept[: max_entries - bank.count]
            truncated = True
        bank.append(rows[kept], units[kept], start + nz[kept])
        if truncated:
            break
    s = bank.count
    return PSCBank(entries=bank.rows[:s].copy(), count=s, gamma=gamma, indices=bank.indices[:s].copy(),
                   truncated=truncated)


def build_per_model(features_by_model: Mapping[str, object], gammas: Mapping[str, float] | None = None,
                    **kwargs) -> dict[str, PSCBank]:
    """One PSC bank per model.

    Args:
      features_by_model: model name -> [..., D_m] features.
      gammas: model name -> threshold; default :data:`M3_GAMMAS`. Every model needs one.
      **kwargs: passed to :func:`build` (chunk, max_entries, initial_capacity).
    Returns:
      model name -> PSCBank (entries [M, D] of that model).
    """
    gammas = M3_GAMMAS if gammas is None else gammas
    missing = [name for name in features_by_model if name not in gammas]
    if missing:
        raise KeyError(f"no PSC gamma for model(s) {missing}; known: {sorted(gammas)}")
    return {name: build(feats, gammas[name], **kwargs) for name, feats in features_by_model.items()}
