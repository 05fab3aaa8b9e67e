"""scripts/gpu/queue.sh: a session's plan run step after step across calls of the device's time limit, and
scripts/gpu/together.sh, commands at once (both run on the GPU machine; their logic is bash, tested here)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
QUEUE, TOGETHER = ROOT / "scripts" / "gpu" / "queue.sh", ROOT / "scripts" / "gpu" / "together.sh"


def _queue(plan: Path, state: Path, out: Path, budget: int = 60, cwd: Path | None = None,
           **env_extra: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "QUEUE_STATE": str(state), "OUT": str(out), "BUDGET": str(budget), **env_extra}
    return subprocess.run(["bash", str(QUEUE), str(plan)], capture_output=True, text=True, env=env, timeout=120,
                          cwd=cwd)


def test_a_plan_goes_on_where_the_last_call_stopped_and_passes_a_failed_step_over(tmp_path):
    marker = tmp_path / "second-call"
    plan = tmp_path / "session.plan"
    plan.write_text(f"""# a comment, then steps
first: echo made > $OUT/first.txt
later: [ -f {marker} ] || exit 75; echo "budget $BUDGET" > $OUT/later.txt
broken: exit 3

last: echo last
""")
    state, out = tmp_path / "state", tmp_path / "out"
    r = _queue(plan, state, out)
    assert r.returncode == 0, r.stderr
    assert "later goes on in the next call" in r.stdout and "== broken" not in r.stdout   # stopped there
    assert (state / "first.done").is_file() and not (state / "later.done").exists()

    marker.touch()
    r = _queue(plan, state, out)
    assert "== first: done before" in r.stdout                       # not run again
    assert (state / "later.done").is_file() and (state / "broken.failed").read_text().strip() == "3"
    assert "echo last" in r.stdout and (state / "last.done").is_file()   # a failed step does not stop the plan
    assert "1 failed" in r.stdout
    # every step's OUT comes back in one tarball, accumulated over the calls, and the log as it ran
    with tarfile.open(out / "queue.tgz") as t:
        names = {Path(n).as_posix().lstrip("./") for n in t.getnames()}
    assert {"first/first.txt", "later/later.txt"} <= names
    assert "== later" in (out / "queue.log").read_text()

    r = _queue(plan, state, out)
    assert "== broken: failed before, left" in r.stdout and "== last: done before" in r.stdout


def test_files_too_large_to_bring_back_are_left_out_of_the_tarball_by_name_and_the_rest_comes_back(tmp_path):
    # random bytes do not compress: a 300 kB file cannot fit a 100 kB tarball, the results beside it can
    plan = tmp_path / "big.plan"
    # (a name tar would read as a pattern, and one with a space)
    plan.write_text("study: head -c 300000 /dev/urandom > \"$OUT/report [1].tgz\"; echo 0.767 > $OUT/results.csv\n"
                    "later: echo done > \"$OUT/later step.txt\"\n")
    state, out = tmp_path / "state", tmp_path / "out"
    r = _queue(plan, state, out, QUEUE_TGZ_BYTES="100000")
    assert r.returncode == 0, r.stderr
    assert (out / "queue.tgz").stat().st_size <= 100000
    with tarfile.open(out / "queue.tgz") as t:
        names = {Path(n).as_posix().lstrip("./") for n in t.getnames()}
        left_out = t.extractfile("./LEFT_OUT.txt").read().decode()
    assert {"study/results.csv", "later/later step.txt"} <= names and "study/report [1].tgz" not in names
    assert "study/report [1].tgz" in left_out and "results.csv" not in left_out
    log = (out / "queue.log").read_text()
    assert log.count("report [1].tgz: left out of queue.tgz") == 1      # said once, not after every step
    assert not (out / "queue.tgz.tmp").exists()


def test_what_queue_tgz_cannot_hold_comes_back_in_a_second_tarball(tmp_path):
    # two 60 kB random files do not fit one 150 kB tarball (less its 64 kB margin) together: the second takes one;
    # a 200 kB file fits neither and is named as left out of both (names with a space and a backslash, which
    # tar's file list must take as they are)
    plan = tmp_path / "big.plan"
    plan.write_text("eval: head -c 60000 /dev/urandom > \"$OUT/predictions\\\\n.tgz\"; head -c 60000 /dev/urandom > "
                    "\"$OUT/report 1.tgz\"; head -c 200000 /dev/urandom > $OUT/huge.bin; echo 0.767 > $OUT/results.csv\n")
    for overflow in ("1", "0"):
        state, out = tmp_path / f"state{overflow}", tmp_path / f"out{overflow}"
        r = _queue(plan, state, out, QUEUE_TGZ_BYTES="150000", QUEUE_OVERFLOW=overflow)
        assert r.returncode == 0, r.stderr
        with tarfile.open(out / "queue.tgz") as t:
            first = {Path(n).as_posix().lstrip("./") for n in t.getnames()}
            left_out = t.extractfile("./LEFT_OUT.txt").read().decode()
        assert "eval/results.csv" in first and "eval/huge.bin" not in first
        assert (out / "queue.tgz").stat().st_size <= 150000
        if overflow == "0":
            assert not (out / "queue-2.tgz").exists() and left_out.count("left out of queue.tgz") == 2
            continue
        with tarfile.open(out / "queue-2.tgz") as t:
            second = {Path(n).as_posix().lstrip("./") for n in t.getnames()}
        assert (out / "queue-2.tgz").stat().st_size <= 150000
        big = {"eval/predictions\\n.tgz", "eval/report 1.tgz"}
        assert (state / "out" / "eval" / "predictions\\n.tgz").is_file()        # a backslash in its name
        assert len(second) == 1 and second < big and big - second <= first       # each big file in one tarball
        assert f"{next(iter(second))}: in queue-2.tgz" in left_out
        assert "eval/huge.bin: left out of queue.tgz and queue-2.tgz" in left_out
        assert not (out / "queue-2.tgz.tmp").exists()


@pytest.mark.slow
def test_a_step_cut_off_by_the_budget_goes_on_next_call_and_a_bad_plan_is_refused(tmp_path):
    plan = tmp_path / "slow.plan"
    plan.write_text("slow: sleep 120\n")
    r = _queue(plan, tmp_path / "state", tmp_path / "out", budget=46)   # 31 s for the step, then it is cut
    assert "== slow: exit 124" in r.stdout and "slow goes on in the next call" in r.stdout
    assert not (tmp_path / "state" / "slow.done").exists() and not (tmp_path / "state" / "slow.failed").exists()

    twice = tmp_path / "twice.plan"
    twice.write_text("a: true\na: true\n")
    r = _queue(twice, tmp_path / "s2", tmp_path / "o2")
    assert r.returncode == 2 and "step a twice" in r.stdout

    # '#' starts a comment in a plan, also inside ${f##*_}: what is left is not a command, and nothing runs
    cut = tmp_path / "cut.plan"
    cut.write_text("first: touch ran\nsecond: for f in x_y; do echo ${f##*_}; done\n")
    r = _queue(cut, tmp_path / "s3", tmp_path / "o3", cwd=tmp_path)
    assert r.returncode == 2 and "step second" in r.stdout and "not a whole bash command" in r.stdout
    assert not (tmp_path / "ran").exists()


def test_together_reports_the_worst_of_its_commands(tmp_path):
    def together(*cmds: str) -> int:
        return subprocess.run(["bash", str(TOGETHER), *cmds], capture_output=True, text=True, timeout=60).returncode

    assert together("true", "true") == 0
    assert together("true", "exit 75") == 75          # one stopped for time: call again
    assert together("exit 75", "exit 3") == 1         # one failed


LANES = ROOT / "scripts" / "gpu" / "lanes.sh"


def test_lanes_split_the_gpus_run_joined_plans_in_order_and_resume_each_lane(tmp_path):
    gate = tmp_path / "second-call"
    first, second, third = tmp_path / "a.plan", tmp_path / "b.plan", tmp_path / "c.plan"
    first.write_text("tests: echo ran-tests\nsee: echo \"gpus $CUDA_VISIBLE_DEVICES\" > $OUT/gpus.txt\n")
    # a step the lane's first plan already has (same name, same command) runs once; the second plan's own
    # step waits for a call
    second.write_text(f"tests: echo ran-tests  # the same command\nslow: [ -f {gate} ] || exit 75; echo b-slow\n")
    third.write_text("see: echo \"gpus $CUDA_VISIBLE_DEVICES\" > $OUT/gpus.txt\n")
    env = {**os.environ, "QUEUE_STATE": str(tmp_path / "state"), "OUT": str(tmp_path / "out"), "BUDGET": "60",
           "CUDA_VISIBLE_DEVICES": "0,1,2,3,4", "PYTHON": sys.executable}

    def call() -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(LANES), f"{first}+{second}", str(third)], capture_output=True,
                              text=True, env=env, timeout=120)

    r = call()
    assert r.returncode == 0, r.stdout + r.stderr
    assert "lane1 on GPUs 0,1,2:" in r.stdout and "lane2 on GPUs 3,4:" in r.stdout
    lane1 = (tmp_path / "out" / "lane1" / "queue.log").read_text()
    assert lane1.splitlines().count("ran-tests") == 1 and "slow goes on in the next call" in lane1
    for lane, gpus in (("lane1", "0,1,2"), ("lane2", "3,4")):
        with tarfile.open(tmp_path / "out" / lane / "queue.tgz") as t:
            assert t.extractfile("./see/gpus.txt").read().decode().strip() == f"gpus {gpus}"

    gate.touch()
    call()
    lane1 = (tmp_path / "out" / "lane1" / "queue.log").read_text()
    assert "== see: done before" in lane1 and "b-slow" in lane1

    env["CUDA_VISIBLE_DEVICES"] = "7"                  # fewer GPUs than lanes: they share it
    env["QUEUE_STATE"], env["OUT"] = str(tmp_path / "state2"), str(tmp_path / "out2")
    r = call()
    assert "lane1 on GPUs 7:" in r.stdout and "lane2 on GPUs 7:" in r.stdout
    env["CUDA_VISIBLE_DEVICES"] = ""                   # none (a CPU dry run): every lane runs, without GPUs
    env["QUEUE_STATE"], env["OUT"] = str(tmp_path / "state3"), str(tmp_path / "out3")
    r = call()
    assert r.returncode == 0 and "lane1 on GPUs (none):" in r.stdout, r.stdout + r.stderr
    with tarfile.open(tmp_path / "out3" / "lane2" / "queue.tgz") as t:
        assert t.extractfile("./see/gpus.txt").read().decode().strip() == "gpus"


def test_lanes_refuse_a_bad_plan_before_any_lane_starts(tmp_path):
    started = tmp_path / "started"
    first = tmp_path / "a.plan"
    first.write_text(f"go: touch {started}\ntrain: echo one\n")
    other = tmp_path / "b.plan"
    other.write_text("train: echo another\n")          # the same name, another command: one state, two steps
    env = {**os.environ, "QUEUE_STATE": str(tmp_path / "state"), "OUT": str(tmp_path / "out"), "BUDGET": "60",
           "CUDA_VISIBLE_DEVICES": "0,1", "PYTHON": sys.executable}
    for lanes, message in (([f"{first}+{other}"], "step 'train' of"), ([str(first), str(tmp_path / "no.plan")],
                                                                          "no plan file")):
        r = subprocess.run(["bash", str(LANES), *lanes], capture_output=True, text=True, env=env, timeout=60)
        assert r.returncode == 2 and message in r.stderr and "no lane started" in r.stderr
        assert not started.exists()                     # not even the good lane ran


@pytest.mark.parametrize("plan", sorted((ROOT / "scripts" / "gpu" / "plans").glob("*.plan")), ids=lambda p: p.name)
def test_every_committed_plan_reads_as_a_plan_and_its_scripts_exist(plan):
    check = subprocess.run(["bash", str(QUEUE), "--check", str(plan)], capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr
    # every project script a step names is there (a renamed script would fail only on the GPU machine)
    for script in re.findall(r"(?:scripts|benchmarks)/[\w/.-]+\.(?:sh|py|plan)", plan.read_text()):
        assert (ROOT / script).is_file(), f"{plan.name} names {script}, which does not exist"


DETACHED = ROOT / "scripts" / "gpu" / "detached.sh"


def test_a_detached_run_goes_on_after_the_call_returns_and_a_later_call_brings_its_results(tmp_path):
    starts, gate = tmp_path / "starts.txt", tmp_path / "gate"
    plan = tmp_path / "a.plan"
    # a step longer than the first call (it waits for the gate, opened after the call): it runs once, across the
    # calls, never cut and started again. The call waits BUDGET - 15 = 5 s, time for the run to start on a busy CPU.
    plan.write_text(f"long: echo start >> {starts}; while [ ! -f {gate} ]; do sleep 0.2; done; "
                    "echo \"budget $BUDGET\" > $OUT/long.txt\n"
                    "after: echo after > $OUT/after.txt\n")
    env = {**os.environ, "QUEUE_STATE": str(tmp_path / "state"), "BUDGET": "20", "RUN_BUDGET": "120",
           "CUDA_VISIBLE_DEVICES": "", "PYTHON": sys.executable}

    def call(out: str, *plans: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(DETACHED), *plans], capture_output=True, text=True,
                              env={**env, "OUT": str(tmp_path / out)}, timeout=60)

    r = call("out1", str(plan))
    assert r.returncode == 0 and "started the plans" in r.stdout and "call again" in r.stdout, r.stdout + r.stderr
    pid = int((tmp_path / "state" / "detached.pid").read_text())
    assert os.getsid(pid) != os.getsid(0)           # its own process session: the device leaves it running
    assert "== long" in (tmp_path / "out1" / "lane1" / "queue.log").read_text()   # what ran so far came back
    gate.touch()
    for _ in range(100):                             # no call is running now: the run goes on by itself
        if (tmp_path / "state" / "detached.rc").exists():
            break
        time.sleep(0.1)
    assert (tmp_path / "state" / "detached.rc").read_text().strip() == "0"
    r = call("out2", str(plan))
    assert r.returncode == 0 and "ended in an earlier call (exit 0)" in r.stdout, r.stdout + r.stderr
    assert starts.read_text().splitlines() == ["start"]                   # the step ran once
    with tarfile.open(tmp_path / "out2" / "lane1" / "queue.tgz") as t:
        assert t.extractfile("./long/long.txt").read().decode().split()[0] == "budget"
        assert t.extractfile("./after/after.txt").read().decode().strip() == "after"
    assert "every step" in (tmp_path / "out2" / "detached.log").read_text()

    bad = tmp_path / "bad.plan"
    bad.write_text("a: echo one\na: echo two\n")
    env["QUEUE_STATE"] = str(tmp_path / "state2")
    r = call("out3", str(bad))
    assert r.returncode == 2 and "nothing started" in r.stderr and not (tmp_path / "state2" / "detached.pid").exists()


def test_a_detached_run_whose_wrapper_was_killed_is_still_waited_on_and_not_started_twice(tmp_path):
    import signal

    starts = tmp_path / "starts.txt"
    gate = tmp_path / "gate"
    plan = tmp_path / "a.plan"
    plan.write_text(f"long: echo start >> {starts}; while [ ! -f {gate} ]; do sleep 0.2; done\n")
    env = {**os.environ, "QUEUE_STATE": str(tmp_path / "state"), "BUDGET": "16", "RUN_BUDGET": "120",
           "CUDA_VISIBLE_DEVICES": "", "PYTHON": sys.executable}

    def call(out: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(DETACHED), str(plan)], capture_output=True, text=True,
                              env={**env, "OUT": str(tmp_path / out)}, timeout=60)

    assert "started the plans" in call("out1").stdout
    os.kill(int((tmp_path / "state" / "detached.pid").read_text()), signal.SIGKILL)   # the run's own processes live
    r = call("out2")
    assert "run since an earlier call" in r.stdout and "call again" in r.stdout, r.stdout + r.stderr
    assert starts.read_text().splitlines() == ["start"]                  # not started a second time
    gate.touch()
    for _ in range(100):      # the step ends; its wrapper gone, no exit status: a call goes on from the queue's state
        r = call("out3")
        if "call again" not in r.stdout:
            break
    assert r.returncode == 0 and "the plans ended (exit 0)" in r.stdout, r.stdout + r.stderr
    assert starts.read_text().splitlines() == ["start"]                  # the finished step was not run again


def test_the_graphed_readers_hold_only_when_tested_captured_and_faster(tmp_path):
    script = ROOT / "scripts" / "gpu" / "reader_graphs_ok.py"
    tests_ok, off = tmp_path / "tests-ok", tmp_path / "off"

    def verdict(*results: dict, tests: bool = True, holds: bool = False) -> str:
        files = []
        for i, r in enumerate(results):
            files.append(tmp_path / f"r{i}.json")
            files[-1].write_text(json.dumps(r))
        tests_ok.unlink(missing_ok=True)
        if tests:
            tests_ok.touch()
        off.write_text("unchecked\n")                  # as the plans leave it before the check
        r = subprocess.run([sys.executable, str(script), *map(str, files), "--tests-ok", str(tests_ok),
                            "--off", str(off)], capture_output=True, text=True, timeout=60)
        assert r.returncode == (0 if holds else 1), r.stdout + r.stderr
        return r.stdout

    fast = {"model": "base2", "graphed": {"captured": True}, "graphed_over_one_batch": 4.1}
    assert "hold: base2 4.1x" in verdict(fast, dict(fast, model="base1"), holds=True) and not off.exists()
    assert "GPU tests did not pass" in verdict(fast, tests=False) and "GPU tests" in off.read_text()
    assert "under 1.2x" in verdict(fast, dict(fast, model="base3", graphed_over_one_batch=1.1)) and off.is_file()
    assert "not captured" in verdict(dict(fast, graphed={"captured": False, "capture_failed": "x"}))
    assert "no reader was timed" in verdict()


@pytest.mark.parametrize("plan", sorted((ROOT / "scripts" / "gpu" / "plans").glob("*.plan")), ids=lambda p: p.stem)
def test_every_shipped_plan_is_one_the_queue_accepts(plan):
    # a plan the queue refuses costs a GPU session's staging before anyone sees it
    result = subprocess.run(["bash", str(QUEUE), "--check", str(plan)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_a_line_that_is_no_step_is_refused_before_anything_runs(tmp_path):
    for text, message in (("first: true\nthe rest of a comment whose # was lost\n", "is not 'NAME: command'"),
                          ("first: true\nsecond:   \n", "step second in .* has no command"),
                          ("first: true\nIssue 14 goal 4: is the host's memory flat?\n", "bad step name 'Issue 14")):
        plan = tmp_path / "bad.plan"
        plan.write_text(text)
        result = _queue(plan, tmp_path / "state", tmp_path / "out")
        assert result.returncode == 2 and re.search(message, result.stdout + result.stderr)
        assert not (tmp_path / "state" / "first.done").exists()
