"""MQTT topic filters, checked before the service starts (no third-party import: the
command line checks ``--mqtt-topic`` while parsing, before it knows whether the
``[serve]`` extra is installed)."""

from __future__ import annotations

__all__ = ["check_topic_filter"]


def check_topic_filter(topic: str) -> str:
    """``topic`` if it is a valid MQTT subscription filter (MQTT 3.1.1 section 4.7: not
    empty, at most 65 535 bytes of UTF-8 without NUL, ``+`` a whole level, ``#`` a whole
    level and the last); else ``ValueError`` saying which rule it breaks.

    paho raises on an invalid filter only inside its network thread, at the subscription
    after connecting: that ended the thread, and the service ran on without MQTT and
    without a word of why (the service review, ``--mqtt-topic 'a/#/b'``)."""
    if not topic:
        raise ValueError("an empty topic filter")
    try:
        size = len(topic.encode("utf-8"))
    except UnicodeEncodeError:
        raise ValueError(f"topic filter {topic!r} is not valid UTF-8") from None
    if size > 65535:
        raise ValueError(f"topic filter of {size} bytes, more than MQTT's 65535")
    if "\0" in topic:
        raise ValueError(f"topic filter {topic!r} holds a NUL character")
    levels = topic.split("/")
    for i, level in enumerate(levels):
        if "#" in level and (level != "#" or i != len(levels) - 1):
            raise ValueError(f"topic filter {topic!r}: '#' must be a whole level, the "
                             "last one (as in robustloc/measurements/#)")
        if "+" in level and level != "+":
            raise ValueError(f"topic filter {topic!r}: '+' must be a whole level (as in "
                             "robustloc/+/measurements)")
    return topic
