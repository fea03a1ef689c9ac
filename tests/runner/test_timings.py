"""timings.json of a resumed batch covers all of its finished runs: stage seconds summed, each run listed."""

import json
from collections import Counter

from scenegen.runner.pipeline import write_timings


def run(wall, proposals, workers=2):
    return {"wall": wall, "workers": workers, "backend": "local", "proposals": proposals}


def test_a_resumed_batch_sums_its_runs_and_lists_each(tmp_path):
    path = tmp_path / "timings.json"
    write_timings(path, run(10.0, 7), Counter(settle=4.0, propose=1.0), Counter(settle=7.5))
    write_timings(path, run(5.5, 3, workers=1), Counter(settle=2.0, render=1.0), Counter(settle=3.0))
    timing = json.loads(path.read_text())
    assert timing["wall"] == 15.5
    assert timing["stages"] == {"settle": 6.0, "propose": 1.0, "render": 1.0}
    assert timing["cpu"] == {"settle": 10.5}
    assert (timing["workers"], timing["proposals_this_run"]) == (1, 3)  # the last run's
    assert [r["proposals"] for r in timing["runs"]] == [7, 3]
    before = path.read_text()
    write_timings(path, run(0.2, 0), Counter(), Counter())  # a rerun of the complete batch adds nothing
    assert path.read_text() == before


def test_a_file_from_before_runs_existed_counts_as_one_run_and_a_broken_one_is_replaced(tmp_path):
    path = tmp_path / "timings.json"
    old = {"wall": 4.0, "workers": 2, "backend": "local", "stages": {"settle": 3.0}, "proposals_this_run": 5}
    path.write_text(json.dumps(old))
    write_timings(path, run(1.0, 2), Counter(settle=1.0), Counter())
    timing = json.loads(path.read_text())
    assert timing["wall"] == 5.0 and timing["stages"] == {"settle": 4.0}
    assert [r["proposals"] for r in timing["runs"]] == [5, 2]
    odd = '{"wall": 1, "workers": 2, "backend": "local", "stages": {"settle": "x"}}'
    for broken in ("{torn", odd, "[1]"):
        path.write_text(broken)  # not one this code wrote: started anew, the batch's end not lost
        write_timings(path, run(1.0, 2), Counter(settle=1.0), Counter())
        assert json.loads(path.read_text())["stages"] == {"settle": 1.0}
