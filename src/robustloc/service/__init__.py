"""Live positioning service (``robustloc serve``): ingest, epoch assembly, store, API.

Layers: :mod:`~robustloc.service.rows` (parse and validate rows),
:mod:`~robustloc.service.assembly` (epochs from rows in any order),
:mod:`~robustloc.service.processor` (locate or track a block of epochs),
:mod:`~robustloc.service.store` (write-ahead log + Parquet segments),
:mod:`~robustloc.service.engine` (ties them together, thread-safe),
:mod:`~robustloc.service.app` (Starlette HTTP/WebSocket API and the map page),
:mod:`~robustloc.service.mqtt` (MQTT ingest).  Starlette, uvicorn and paho-mqtt come with
the ``[serve]`` extra.
"""
