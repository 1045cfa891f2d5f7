"""Service counters and the Prometheus text exposition (format 0.0.4), without a client
library: a handful of counters, gauges and one histogram."""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence

import numpy as np

#: Latencies kept (a uniform reservoir sample) for the p50/p99 of ``/api/status``.
LATENCY_RESERVOIR = 100_000

#: Upper bounds (s) of the latency histogram's buckets: ready epoch -> position published.
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0)


class Metrics:
    """Thread-safe counters of one service.

    Parameters
    ----------
    anchor_ids : sequence of str
        Anchors, for the per-anchor counters.
    """

    def __init__(self, anchor_ids: Sequence[str]) -> None:
        self._lock = threading.Lock()
        self.started = time.time()
        self.anchor_ids = tuple(anchor_ids)
        m = len(self.anchor_ids)
        self.rows_accepted: dict[str, int] = {}
        self.rows_rejected: dict[str, int] = {}
        self.rows_late = 0
        #: epochs whose every row arrived late, solved all the same (service.assembly)
        self.late_epochs_solved = 0
        self.tags_rebased = 0  # tags whose clock jumped (robustloc.service.assembly)
        self.tags_refused = 0  # new tags beyond serve --max-tags (their rows rejected)
        self.tags_forgotten = 0  # tags silent for serve --forget-after (state dropped)
        self.requests_rejected: dict[str, int] = {}  # reason -> count (401, 413, 429, ...)
        self.positions: dict[str, int] = {}  # status -> count
        self.ws_dropped = 0
        self.heard = np.zeros(m, dtype=np.int64)
        self.anchor_rejected = np.zeros(m, dtype=np.int64)
        self.last_heard = np.full(m, np.nan)
        self.latency_counts = np.zeros(len(LATENCY_BUCKETS_S) + 1, dtype=np.int64)
        self.latency_sum = 0.0
        self._reservoir = np.empty(LATENCY_RESERVOIR)  # uniform sample for quantiles
        self._lat_seen = 0
        self._rng = np.random.default_rng(0)

    def ingest(self, source: str, accepted: int, rejected: int, late: int,
               anchor_col: np.ndarray, rejected_cols: np.ndarray, wall: float) -> None:
        with self._lock:
            self.rows_accepted[source] = self.rows_accepted.get(source, 0) + accepted
            self.rows_rejected[source] = self.rows_rejected.get(source, 0) + rejected
            self.rows_late += late
            if len(anchor_col):
                heard = np.bincount(anchor_col, minlength=len(self.heard))
                self.heard += heard
                self.last_heard[heard > 0] = wall
            if len(rejected_cols):
                self.anchor_rejected += np.bincount(rejected_cols, minlength=len(self.heard))

    def request_rejected(self, reason: str) -> None:
        with self._lock:
            self.requests_rejected[reason] = self.requests_rejected.get(reason, 0) + 1

    def solved(self, statuses: np.ndarray, latency_s: np.ndarray) -> None:
        st, cnt = np.unique(statuses.astype(str), return_counts=True)
        idx = np.searchsorted(LATENCY_BUCKETS_S, latency_s, side="left")
        with self._lock:
            for s, c in zip(st.tolist(), cnt.tolist()):
                self.positions[s] = self.positions.get(s, 0) + c
            self.latency_counts += np.bincount(idx, minlength=len(self.latency_counts))
            self.latency_sum += float(latency_s.sum())
            self._sample(np.asarray(latency_s, dtype=float))

    def _sample(self, x: np.ndarray) -> None:
        """Reservoir sampling (Vitter's algorithm R), vectorized over a block: the k-th
        latency ever seen (1-based) fills slot k-1 while the reservoir is not full, and
        later replaces slot j ~ U{0, k-1} when j < capacity (in order, so a later latency
        drawn for the same slot wins, as in the sequential algorithm)."""
        cap, seen = len(self._reservoir), self._lat_seen
        k = seen + np.arange(1, len(x) + 1)
        fill = k <= cap
        self._reservoir[k[fill] - 1] = x[fill]
        if not fill.all():
            j = self._rng.integers(0, k[~fill])
            keep = j < cap
            # numpy assigns repeated indices in order: the last one drawn stays
            self._reservoir[j[keep]] = x[~fill][keep]
        self._lat_seen = seen + len(x)

    def latency_sample(self) -> np.ndarray:
        """A uniform random sample (at most :data:`LATENCY_RESERVOIR`) of the latencies."""
        with self._lock:
            return self._reservoir[: min(self._lat_seen, len(self._reservoir))].copy()

    def anchor_health(self) -> list[dict]:
        with self._lock:
            out = []
            for i, a in enumerate(self.anchor_ids):
                heard, rej = int(self.heard[i]), int(self.anchor_rejected[i])
                lh = self.last_heard[i]
                out.append({
                    "anchor": a, "rows_heard": heard, "rows_rejected": rej,
                    # (None when nothing was heard: "0.0 %" read as a measured rate)
                    "rejection_rate": rej / (heard + rej) if heard + rej else None,
                    "last_heard": None if np.isnan(lh) else float(lh),
                })
            return out

    def summary(self) -> dict:
        with self._lock:
            lat = self._reservoir[: min(self._lat_seen, len(self._reservoir))]
            return {
                "uptime_s": time.time() - self.started,
                "rows_accepted": sum(self.rows_accepted.values()),
                "rows_rejected": sum(self.rows_rejected.values()),
                "rows_late": self.rows_late,
                "late_epochs_solved": self.late_epochs_solved,
                "tags_rebased": self.tags_rebased,
                "tags_refused": self.tags_refused,
                "tags_forgotten": self.tags_forgotten,
                "requests_rejected": dict(self.requests_rejected),
                "positions": sum(self.positions.values()),
                "latency_p50_s": float(np.percentile(lat, 50)) if len(lat) else None,
                "latency_p99_s": float(np.percentile(lat, 99)) if len(lat) else None,
            }

    def render(self, pending_rows: int, tags: int, solver_errors: int = 0,
               position_store_errors: int = 0) -> str:
        """Prometheus text format (``solver_errors``: the engine's count of processor
        failures, each a defect whose epochs got ``solver_error`` rows or were retried;
        ``position_store_errors``: failed appends of solved positions to the store)."""
        def esc(s: str) -> str:
            return s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")

        lines: list[str] = []

        def family(name: str, kind: str, help_: str) -> None:
            lines.append(f"# HELP {name} {help_}")
            lines.append(f"# TYPE {name} {kind}")

        with self._lock:
            family("robustloc_rows_accepted_total", "counter",
                   "Measurement rows accepted and stored, by ingest source.")
            for src in sorted(set(self.rows_accepted) | {"http"}):
                lines.append(f'robustloc_rows_accepted_total{{source="{src}"}} '
                             f"{self.rows_accepted.get(src, 0)}")
            family("robustloc_rows_rejected_total", "counter",
                   "Malformed measurement rows rejected, by ingest source.")
            for src in sorted(set(self.rows_rejected) | {"http"}):
                lines.append(f'robustloc_rows_rejected_total{{source="{src}"}} '
                             f"{self.rows_rejected.get(src, 0)}")
            family("robustloc_rows_late_total", "counter",
                   "Accepted rows that arrived after their epoch was solved (stored, not "
                   "solved live).")
            lines.append(f"robustloc_rows_late_total {self.rows_late}")
            family("robustloc_late_epochs_solved_total", "counter",
                   "Epochs whose every row arrived late (after later epochs of the tag were "
                   "solved), solved all the same and published with late=true (not with "
                   "--track).")
            lines.append(f"robustloc_late_epochs_solved_total {self.late_epochs_solved}")
            family("robustloc_tags_rebased_total", "counter",
                   "Times a tag's clock jumped (a row more than --time-jump behind its "
                   "newest time, nothing near it for --idle-flush) and its epochs "
                   "restarted from the new time.")
            lines.append(f"robustloc_tags_rebased_total {self.tags_rebased}")
            family("robustloc_tags_refused_total", "counter",
                   "New tags refused because the service holds --max-tags already (their "
                   "rows rejected, counted in robustloc_rows_rejected_total).")
            lines.append(f"robustloc_tags_refused_total {self.tags_refused}")
            family("robustloc_tags_forgotten_total", "counter",
                   "Tags forgotten after --forget-after seconds without a row (their state "
                   "dropped, their stored rows kept; heard again, a tag starts afresh).")
            lines.append(f"robustloc_tags_forgotten_total {self.tags_forgotten}")
            family("robustloc_requests_rejected_total", "counter",
                   "Requests refused as a whole, by reason.")
            for r, c in sorted(self.requests_rejected.items()):
                lines.append(f'robustloc_requests_rejected_total{{reason="{esc(r)}"}} {c}')
            family("robustloc_solver_errors_total", "counter",
                   "Failures of the solver on a block of epochs (a defect; the last reason "
                   "is in /api/status).")
            lines.append(f"robustloc_solver_errors_total {int(solver_errors)}")
            family("robustloc_position_store_errors_total", "counter",
                   "Failed appends of solved positions to the store (disk full); the "
                   "positions were published and are stored with the next append that "
                   "succeeds (or solved again at the next start).")
            lines.append(f"robustloc_position_store_errors_total {int(position_store_errors)}")
            family("robustloc_positions_total", "counter", "Position rows computed, by status.")
            for s, c in sorted(self.positions.items()):
                lines.append(f'robustloc_positions_total{{status="{esc(s)}"}} {c}')
            family("robustloc_position_latency_seconds", "histogram",
                   "Wall time from an epoch becoming ready (past the latency window) to its "
                   "position being stored and published.")
            cum = np.cumsum(self.latency_counts)
            for b, c in zip(LATENCY_BUCKETS_S, cum[:-1]):
                lines.append(f'robustloc_position_latency_seconds_bucket{{le="{b:g}"}} {c}')
            lines.append(f'robustloc_position_latency_seconds_bucket{{le="+Inf"}} {cum[-1]}')
            lines.append(f"robustloc_position_latency_seconds_sum {self.latency_sum:.6f}")
            lines.append(f"robustloc_position_latency_seconds_count {cum[-1]}")
            family("robustloc_anchor_rows_heard_total", "counter",
                   "Accepted rows per anchor.")
            for a, c in zip(self.anchor_ids, self.heard.tolist()):
                lines.append(f'robustloc_anchor_rows_heard_total{{anchor="{esc(a)}"}} {c}')
            family("robustloc_anchor_rows_rejected_total", "counter",
                   "Rejected rows naming a known anchor (bad value, time, tag).")
            for a, c in zip(self.anchor_ids, self.anchor_rejected.tolist()):
                lines.append(f'robustloc_anchor_rows_rejected_total{{anchor="{esc(a)}"}} {c}')
            family("robustloc_ws_messages_dropped_total", "counter",
                   "Position messages not sent to a WebSocket client too slow to keep up.")
            lines.append(f"robustloc_ws_messages_dropped_total {self.ws_dropped}")
        family("robustloc_pending_rows", "gauge", "Rows waiting for their epoch to be ready.")
        lines.append(f"robustloc_pending_rows {pending_rows}")
        family("robustloc_tags", "gauge", "Tags seen.")
        lines.append(f"robustloc_tags {tags}")
        return "\n".join(lines) + "\n"
