""":class:`robustloc.tracking.AutoTracker`: a stream's first epochs choose the links'
offsets, as ``track --link-offsets auto`` chooses on a log's first epochs."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from test_track_link_offsets import LINK_B_M
from test_track_select import _walking_log

from robustloc.tracking import AutoTracker, Tracker
from robustloc.tracking.select import AUTO_MAX_ANCHORS, choose_link_offsets

OPTS = {"sigma": 0.1, "q": 0.05}
SAMPLE = 640  # epochs of the trial: half of the walking log (8 tags x 160 epochs)


def _blocks(ep, size: int):
    return [ep.take(slice(lo, min(lo + size, ep.n_epochs)))
            for lo in range(0, ep.n_epochs, size)]


def _run(trk, ep, size: int) -> pd.DataFrame:
    return pd.concat([trk.step(b) for b in _blocks(ep, size)], ignore_index=True)


@pytest.mark.parametrize("offsets, use", [(4.0, True), (0.0, False)])
@pytest.mark.parametrize("size", [640, 64, 37, 1280])
def test_the_stream_chooses_as_track_chooses_on_the_same_epochs(offsets, use, size):
    """Stepped in blocks of 640, 64, 37 or 1 280 epochs (37 does not divide 640; 1 280 is
    the whole stream in one block), the trial's choice is ``choose_link_offsets``' on the
    same first 640 epochs, with the same scores: a block that crosses the count is cut
    there.  The rows are those of the tracker without the offsets up to the choice and
    those of the chosen tracker, which followed the whole stream, after it (exactly:
    recording, scoring and cutting do not change a row)."""
    a, ep = _walking_log(offsets * LINK_B_M, 1)
    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    rows = _run(trk, ep, size)
    ref = choose_link_offsets(a, ep.take(slice(0, SAMPLE)), **OPTS)
    c = trk.choice
    assert c is not None and c.use is use is ref.use, (c, ref)
    assert (c.t, c.score_with, c.score_without, c.observations, c.epochs) == (
        ref.t, ref.score_with, ref.score_without, ref.observations, ref.epochs)
    assert c.epochs == SAMPLE
    without = Tracker(a, **OPTS).step(ep)
    chosen = Tracker(a, link_offsets=use, **OPTS).step(ep)
    pd.testing.assert_frame_equal(rows.iloc[:SAMPLE], without.iloc[:SAMPLE])
    pd.testing.assert_frame_equal(rows.iloc[SAMPLE:].reset_index(drop=True),
                                  chosen.iloc[SAMPLE:].reset_index(drop=True))
    assert trk.status()["phase"] == "chosen" and trk.status()["used"] is use
    assert trk.tracker.settings.link_offsets is use and not trk.tracker.record


def test_a_large_block_is_tracked_in_pieces_with_the_same_rows(monkeypatch):
    """A block far larger than the trial's pieces: no tracker ever holds the record of
    more than one piece (the trial's memory is bounded by the piece, not by the block
    the service hands over), and the rows and the choice are those of one piece."""
    import robustloc.tracking.auto as auto

    a, ep = _walking_log(4 * LINK_B_M, 1)
    whole = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    ref = whole.step(ep)
    monkeypatch.setattr(auto, "AUTO_SCORE_PIECE", 50)
    held = []
    score = Tracker.predictive_score

    def spy(self, values):
        held.append(self._rows_recorded)
        return score(self, values)

    monkeypatch.setattr(Tracker, "predictive_score", spy)
    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    pd.testing.assert_frame_equal(trk.step(ep), ref)
    assert trk.choice == whole.choice
    assert max(held) == 50 and len(held) == 2 * -(-SAMPLE // 50)


def test_a_failing_tracker_with_offsets_ends_the_trial_and_a_failing_block_changes_nothing(
        monkeypatch):
    """The tracker with the offsets raising: the trial ends with them off and the error
    as the reason, and the rows are the plain tracker's throughout.  The tracker without
    them raising: the step raises and nothing changed (the same state, and the next steps
    give the uninterrupted rows)."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    blocks = _blocks(ep, 80)
    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    trk.step(blocks[0])
    step = Tracker.step

    def broken(self, epochs):
        if self.settings.link_offsets:
            raise FloatingPointError("singular innovation covariance")
        return step(self, epochs)

    monkeypatch.setattr(Tracker, "step", broken)
    rows = trk.step(blocks[1])
    c = trk.choice
    assert c is not None and not c.use and "FloatingPointError" in c.reason
    assert c.epochs == 80 and trk._shadow is None and not trk.tracker.record
    monkeypatch.setattr(Tracker, "step", step)
    rows = pd.concat([rows] + [trk.step(b) for b in blocks[2:]], ignore_index=True)
    plain = Tracker(a, **OPTS).step(ep)
    pd.testing.assert_frame_equal(rows, plain.iloc[80:].reset_index(drop=True))

    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    trk.step(blocks[0])
    before = json.dumps(trk.state_dict())
    calls = []

    def late(self, epochs):
        calls.append(1)
        if len(calls) == 3:  # the plain tracker's second piece: after one piece scored
            raise FloatingPointError("boom")
        return step(self, epochs)

    monkeypatch.setattr("robustloc.tracking.auto.AUTO_SCORE_PIECE", 40)
    monkeypatch.setattr(Tracker, "step", late)
    with pytest.raises(FloatingPointError):
        trk.step(blocks[1])
    monkeypatch.setattr(Tracker, "step", step)
    assert json.dumps(trk.state_dict()) == before and trk.trial_epochs == 80
    ref = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    ref.step(blocks[0])
    for b in blocks[1:]:
        pd.testing.assert_frame_equal(trk.step(b), ref.step(b))
    assert trk.choice == ref.choice


def test_a_saved_state_and_a_rollback_continue_the_trial_exactly():
    """Saved as JSON mid-trial and loaded into a new AutoTracker, and rolled back over the
    block that made the choice and stepped again: the same rows and the same choice as
    one uninterrupted stream."""
    a, ep = _walking_log(4 * LINK_B_M, 2)
    blocks = _blocks(ep, 80)
    whole = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    ref = pd.concat([whole.step(b) for b in blocks], ignore_index=True)
    assert whole.choice is not None and whole.choice.use

    first = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    out = [first.step(b) for b in blocks[:5]]
    assert first.choice is None and first.status() == {
        "mode": "auto", "phase": "trial", "epochs": 400, "sample_epochs": SAMPLE}
    saved = json.loads(json.dumps(first.state_dict()))
    second = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    second.load_state_dict(saved)
    out += [second.step(b) for b in blocks[5:7]]
    before = second.checkpoint()
    bad = second.step(blocks[7])  # the block that reaches 640 epochs: the choice
    assert second.choice is not None and second.choice.use
    second.rollback(before)
    assert second.choice is None and second.trial_epochs == 560
    again = second.step(blocks[7])
    pd.testing.assert_frame_equal(bad, again)
    out.append(again)
    saved = json.loads(json.dumps(second.state_dict()))  # after the choice
    third = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    third.load_state_dict(saved)
    assert third.choice == second.choice
    out += [third.step(b) for b in blocks[8:]]
    pd.testing.assert_frame_equal(pd.concat(out, ignore_index=True), ref)


def test_forgetting_tags_during_the_trial_forgets_them_in_both_trackers():
    """A tag forgotten mid-trial starts afresh in both trackers (the chosen one then
    holds no trace of it), and the others go on as before."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    blocks = _blocks(ep, 80)
    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    for b in blocks[:3]:
        trk.step(b)
    tag = str(ep.tag[0])
    assert trk.forget([tag]) == 1 and tag not in trk.tags
    ref = Tracker(a, **OPTS)
    for b in blocks[:3]:
        ref.step(b)
    ref.forget([tag])
    pd.testing.assert_frame_equal(trk.step(blocks[3]), ref.step(blocks[3]))
    for b in blocks[4:]:
        trk.step(b)
    assert trk.choice is not None and trk.choice.use


def test_no_trial_where_track_runs_none():
    """The tag's common range offset estimated instead, or more anchors than auto
    chooses on: off from the start, the reason given, one tracker (the plain one's
    rows)."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    trk = AutoTracker(a, sample_epochs=SAMPLE, range_offset=True, **OPTS)
    assert trk.choice is not None and not trk.choice.use
    assert "range offset" in trk.choice.reason
    pd.testing.assert_frame_equal(trk.step(ep),
                                  Tracker(a, range_offset=True, **OPTS).step(ep))
    still = AutoTracker(a, sample_epochs=SAMPLE, **{**OPTS, "model": "static"})
    assert still.choice is not None and not still.choice.use
    assert "--model static" in still.choice.reason
    many = pd.DataFrame({"anchor": [f"a{i}" for i in range(AUTO_MAX_ANCHORS + 1)],
                         "x": np.cos(np.arange(AUTO_MAX_ANCHORS + 1.0)) * 10,
                         "y": np.sin(np.arange(AUTO_MAX_ANCHORS + 1.0)) * 10})
    c = AutoTracker(many, sigma=0.1).choice
    assert c is not None and not c.use and f"{AUTO_MAX_ANCHORS + 1} anchors" in c.reason


def test_a_stream_shorter_than_the_sample_keeps_the_plain_rows():
    """Before the choice the rows are the plain tracker's, and the status says how far
    the trial has come."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    trk = AutoTracker(a, sample_epochs=10_000, **OPTS)
    rows = _run(trk, ep, 100)
    pd.testing.assert_frame_equal(rows, Tracker(a, **OPTS).step(ep))
    assert trk.choice is None
    assert trk.status() == {"mode": "auto", "phase": "trial", "epochs": ep.n_epochs,
                            "sample_epochs": 10_000}


def test_bad_settings_and_states_are_refused_and_change_nothing():
    a, ep = _walking_log(0 * LINK_B_M, 1)
    with pytest.raises(TypeError, match="link_offsets"):
        AutoTracker(a, link_offsets=True)
    with pytest.raises(TypeError, match="record"):
        AutoTracker(a, record=True)
    for bad in (0, -5, 2.5, True, "100"):
        with pytest.raises(ValueError, match="sample_epochs"):
            AutoTracker(a, sample_epochs=bad)
    with pytest.raises(TypeError, match="unknown tracker option"):
        AutoTracker(a, link_offset=True)
    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    trk.step(ep.take(slice(0, 100)))
    saved = trk.state_dict()
    plain = Tracker(a, **OPTS)
    plain.step(ep.take(slice(0, 100)))
    for state, match in ((plain.state_dict(), "not an auto tracker"),
                         ({**saved, "version": 9}, "version"),
                         ({**saved, "scores": None}, "lacks its shadow"),
                         ({**saved, "scores": {**saved["scores"], "with": [1.0]}},
                          "do not cover"),
                         ({**saved, "epochs": -50}, "epochs must be a count"),
                         ({**saved, "epochs": 99}, "do not cover"),
                         ({k: v for k, v in saved.items() if k != "live"}, "lacks")):
        other = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
        other.step(ep.take(slice(0, 50)))
        keep = other.state_dict()
        with pytest.raises(ValueError, match=match):
            other.load_state_dict(state)
        assert other.state_dict() == keep
    with pytest.raises(TypeError):
        trk.load_state_dict([])
    with pytest.raises(TypeError):
        trk.rollback({})
    # not Epochs: the tracker's own message (an AttributeError before), nothing changed
    keep = json.dumps(trk.state_dict())
    with pytest.raises(TypeError, match="epochs must be robustloc.io.tables.Epochs"):
        trk.step(pd.DataFrame({"time": [1.0], "tag": ["t"], "anchor": ["a0"], "range": [1.0]}))
    assert json.dumps(trk.state_dict()) == keep


def test_a_trial_restarted_with_a_shorter_sample_chooses_on_its_first_epochs():
    """Saved after 400 epochs, loaded with a sample of 300: the choice is made at once, on
    the first 300 epochs (``choose_link_offsets`` on them); a choice already made keeps
    the sample it was made on."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    trk = AutoTracker(a, sample_epochs=SAMPLE, **OPTS)
    for b in _blocks(ep.take(slice(0, 400)), 80):
        trk.step(b)
    short = AutoTracker(a, sample_epochs=300, **OPTS)
    short.load_state_dict(json.loads(json.dumps(trk.state_dict())))
    ref = choose_link_offsets(a, ep.take(slice(0, 300)), **OPTS)
    assert short.choice is not None and short.choice.t == ref.t and short.choice.epochs == 300
    again = AutoTracker(a, sample_epochs=5000, **OPTS)
    again.load_state_dict(json.loads(json.dumps(short.state_dict())))
    assert again.choice == short.choice and again.sample_epochs == 300
