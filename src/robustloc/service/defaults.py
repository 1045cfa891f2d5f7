"""Default settings of the live service, importable without its optional dependencies
(``robustloc serve --help`` and the command list must work on a core install)."""

#: Default latency window (s): an epoch is solved once its tag's newest time is this much
#: later, so rows still in flight are included.  0.5 s covers the 100-500 ms reporting
#: intervals of BLE/UWB gateways.
DEFAULT_LATENCY_WINDOW_S = 0.5
#: Default wall-clock idle time (s) after which a silent tag's pending epochs are solved.
DEFAULT_IDLE_FLUSH_S = 2.0
#: Default time jump (s) that re-bases a tag (:mod:`robustloc.service.assembly`): a row
#: an hour behind its tag's newest time, the tag silent near that time for the idle
#: flush, means the tag's clock jumped (a restart from 0, or one row far ahead), not a
#: delayed row.
DEFAULT_TIME_JUMP_S = 3600.0
#: Default largest accepted body or WebSocket message (bytes): 32 MiB, ~400 000 rows.
DEFAULT_MAX_BODY_BYTES = 32 * 1024 * 1024
#: Default ingest rate limit per client address (rows/s, token bucket holding 2 s).
DEFAULT_RATE_LIMIT_ROWS = 1_000_000.0
#: Most rows one body may hold (a valid row takes at least ~40 bytes, so a body within the
#: default size limit holds fewer): more is refused as a whole (413) before validation.
MAX_ROWS_PER_BODY = 1_000_000
#: Bodies decoded row by row at once (those the one-pass decoder does not take: a body
#: with a bad row, NDJSON); the others wait their turn.  Each holds its rows as Python
#: objects until validated: one body of a million ``{}`` lines raised the server's peak
#: by 330 MB, six at once by 757 MB unbounded and 530 MB with two at a time (the
#: validation is one at a time anyway, under the ingest lock).
MAX_CONCURRENT_ROW_PARSES = 2
#: ``GET /api/positions`` queries read and answered at once (the store read, the frame and
#: the JSON body, in worker threads of their own, not the pool that ingest uses); the
#: others wait their turn.  Each held a frame of every matching row and its body: 8 at
#: once over a store of 125 000 positions raised the server's peak by 660-680 MiB and
#: held ``/healthz`` for up to 2.6 s and a POST of rows for up to 4.2 s (the serve
#: review; two at a time in their threads: 170-250 MiB, 50-180 ms and 100-240 ms).
MAX_CONCURRENT_POSITION_READS = 2
#: Rejected rows listed in a reply (``rejected``); ``n_rejected`` counts them all.
MAX_REJECTED_LISTED = 1000
#: Seconds a client may take to send a body once its request started; then 408.
DEFAULT_BODY_TIMEOUT_S = 60.0
#: Seconds a connection may take from its start (or its request's first byte) to its
#: request's last header line; then it is closed (:mod:`robustloc.service.protocol`).
DEFAULT_HEADER_TIMEOUT_S = 10.0
#: Default most tags one service holds state for (``serve --max-tags``): each costs some
#: 1.8 kB (locate) to 4 kB (``--track``) for as long as the service runs, so a gateway
#: sending random ids grew the service by 0.9 GB per 200 000 (the service review).  Rows
#: of a tag beyond it are refused, each with its reason.
DEFAULT_MAX_TAGS = 100_000
#: Default wall-clock seconds after which a silent tag is forgotten (``serve
#: --forget-after``): 7 days.  Its state goes (assembly watermarks, filter, its row of
#: ``/api/latest``); its stored rows stay.  A site whose tags come and go (visitors'
#: badges) then holds only the tags heard in the last week, and never reaches --max-tags
#: for tags long gone.
DEFAULT_FORGET_AFTER_S = 7 * 86400.0
