"""Resume with repairs: only the unfinished last index's repair rows are cut from the rejection log."""

from __future__ import annotations

import json

from scenegen.store.batch import _unfinished_repairs_cut


def rows(*spec):
    return [{"proposal_index": i, "label": "collision", **({"repaired": True} if r else {})} for i, r in spec]


def test_only_the_last_unfinished_index_is_cut(tmp_path):
    log = tmp_path / "rejections.jsonl"
    # index 3 ended accepted after two repairs (its end is a scene), index 4 was killed mid-repair
    before = rows((2, False), (3, True), (3, True), (4, True))
    kept = _unfinished_repairs_cut(log, before, [{"proposal_index": 3}])
    assert kept == before[:3]
    assert [json.loads(line) for line in log.read_text().splitlines()] == kept
    # the last index ended accepted: nothing to cut, the log is not rewritten
    log.unlink()
    assert _unfinished_repairs_cut(log, before[:3], [{"proposal_index": 3}]) == before[:3]
    assert not log.exists()
    # the last index ended rejected (its end row has no `repaired`): nothing to cut
    ended = rows((4, True), (4, False))
    assert _unfinished_repairs_cut(log, ended, []) == ended
    # nothing of the last index ended: all its rows go
    assert _unfinished_repairs_cut(log, rows((3, True), (3, True)), []) == []
