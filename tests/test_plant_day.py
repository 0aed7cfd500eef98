"""A plant's day as run: the default ``calibrate -o`` writes the current plant (every record, expected error
from validation inside them), an update after one new day reads only that day's files, the stored choices are
read (not recomputed), and a killed or concurrent update leaves the plant intact."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from helpers.cli import assert_one_line_error, run_cli

from heliotwin.calibrate.twinstate import THRESHOLD_KEY, seen_record_ids
from heliotwin.io import paint as P
from heliotwin.io.scenario import load_scenario
from heliotwin.simulate import SimulationSettings, simulate_plant, write_paint_folder
from heliotwin.workflows.update import update

OLD_NS = 1_600_000_000 * 10**9
DAY = 86400.0


def _age(folder):
    for base, _, files in os.walk(folder):
        for f in files:
            os.utime(os.path.join(base, f), ns=(OLD_NS, OLD_NS))


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """A small simulated plant (6 heliostats, ~1 year of records) split into "until yesterday" and "today"."""
    root = tmp_path_factory.mktemp("day")
    sim = simulate_plant(SimulationSettings(heliostats=6, seed=11, years=1.0, records_per_month=6))
    full = write_paint_folder(sim, root / "full")
    _age(full)
    return full


def _split_at_last_day(full, dest):
    """A copy of ``full`` without its last day's records (returned: [(path in dest, file in full)]) and the
    metadata rows of that day."""
    shutil.copytree(full, dest)
    meta = os.path.join(dest, "metadata", "calibration-metadata.csv")
    lines = open(meta).read().splitlines(keepends=True)
    from heliotwin.io.records import parse_time
    times = {ln.split(",")[0]: parse_time(ln.rstrip("\n").split(",")[-1]) for ln in lines[1:]}
    last = max(t for t in times.values() if np.isfinite(t))
    today = {rid for rid, t in times.items() if np.isfinite(t) and t > last - DAY}
    moved = []
    for hid in P.list_heliostats(dest):
        cal = os.path.join(dest, hid, "Calibration")
        for f in os.listdir(cal):
            if f.split("-")[0] in today:
                os.remove(os.path.join(cal, f))
                moved.append((os.path.join(cal, f), os.path.join(full, hid, "Calibration", f)))
    with open(meta, "w") as fh:
        fh.write("".join(ln for ln in lines if ln.split(",")[0] not in today))
    _age(dest)
    tail = [ln for ln in lines[1:] if ln.split(",")[0] in today]
    return moved, tail, meta


def _grow(moved, tail, meta):
    for dest, src in moved:
        shutil.copy(src, dest)
        os.utime(dest, ns=(OLD_NS + 5 * 10**9,) * 2)
    with open(meta, "a") as fh:
        fh.write("".join(tail))
    os.utime(meta, ns=(OLD_NS + 5 * 10**9,) * 2)


def test_default_calibrate_writes_the_current_plant(plant, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("HELIOTWIN_CACHE_DIR", str(tmp_path / "cache"))
    out, js = tmp_path / "a.h5", tmp_path / "a.json"
    code, text, err = run_cli(capsys, "calibrate", "--paint", plant, "--min-records", 20, "-o", out, "--json", js,
                              "--no-plots")
    assert code == 0, err
    report = json.loads(js.read_text())
    ds = P.load_paint(plant)
    usable = set(ds.records.record_id.tolist())
    seen = seen_record_ids(load_scenario(out))
    assert seen == usable  # the written plant saw every usable record, the latest ones included
    assert report["written_plant"]["records_fitted"] == len(usable)
    expected = report["expected_error"]
    assert expected["holdout_records"] == 10 and 0 < expected["median_of_mean_mrad"] < 2.0
    assert report["overall"]["median_of_mean_test_mrad"] == expected["median_of_mean_mrad"]
    assert "expected error" in text and "every record" in text
    # bagged or not, a random walk or not, chosen by that validation; the plant was fitted as chosen
    choice = report["current_settings_choice"]
    assert choice["candidates"] == ["static", "static, 10 bags", "random-walk offset"]
    for test in choice["tests"]:
        assert test["better"] + test["worse"] + test["ties"] == expected["heliostats_validated"]
        assert test["taken"] == (test["p"] < 0.05)
    taken = [t["candidate"] for t in choice["tests"] if t["taken"]]
    assert choice["chosen"] == (taken[-1] if taken else "static")
    info = report["overall"]["method_info"]
    assert info["bags"] == (10 if choice["chosen"] == "static, 10 bags" else 0)
    assert info["drift_model"] == ("kalman" if choice["chosen"] == "random-walk offset" else "none")
    assert expected["median_of_mean_mrad"] == choice["median_mrad"][choice["chosen"]]
    # the predictive interval calibrated on the same held-out records, and stored with the plant's posterior
    iv = choice["interval"]
    assert abs(iv["coverage"] - 0.9) <= abs(iv["uncalibrated_coverage"] - 0.9)
    posterior = load_scenario(out).learned["calibration"]["posterior"]
    assert float(posterior["drift_rad"].reshape(-1)[0]) == pytest.approx(1e-3 * iv["drift_mrad"])
    # the updates' threshold is learned here, on those records, and stored
    cal = load_scenario(out).learned["calibration"]
    assert float(cal[THRESHOLD_KEY]["threshold"][0]) > 0 and int(cal[THRESHOLD_KEY]["validation_records"][0]) > 100


def test_a_study_protocol_says_its_plant_saw_only_the_training_part(plant, tmp_path, capsys):
    out, js = tmp_path / "s.h5", tmp_path / "s.json"
    code, _, err = run_cli(capsys, "calibrate", "--paint", plant, "--min-records", 20,  # --train: chrono study
                           "--train", 25, "-o", out, "--json", js, "--no-plots")
    assert code == 0, err
    report = json.loads(js.read_text())
    assert "training part" in report["written_plant"]["records"] and "expected_error" not in report
    assert report["config"]["split"] == "chrono"
    seen = seen_record_ids(load_scenario(out))
    assert len(seen) == 25 * report["overall"]["n_heliostats"]


def test_train_with_the_current_split_is_a_one_line_error(plant, tmp_path, capsys):
    code, _, err = run_cli(capsys, "calibrate", "--paint", plant, "--split", "current", "--train", 30, "-o",
                           tmp_path / "x.h5")
    assert_one_line_error(code, err, "--train", "--split")
    assert not (tmp_path / "x.h5").exists()


@pytest.fixture(scope="module")
def calibrated(plant, tmp_path_factory):
    """The plant until yesterday, calibrated (the current plant), and what arrives today."""
    root = tmp_path_factory.mktemp("cal")
    moved, tail, meta = _split_at_last_day(plant, root / "plant")
    env = {**os.environ, "HELIOTWIN_CACHE_DIR": str(root / "cache"), "HELIOTWIN_CACHE": "1"}
    out = root / "a.h5"
    subprocess.run([sys.executable, "-m", "heliotwin", "calibrate", "--paint", str(root / "plant"), "--min-records",
                    "20", "-o", str(out), "--quiet"], check=True, env=env)
    assert moved, "the simulated plant has records on its last day"
    return {"root": root, "folder": root / "plant", "moved": moved, "tail": tail, "meta": meta, "scenario": out,
            "env": env}


def _run(args, env, **kw):
    return subprocess.run([sys.executable, "-m", "heliotwin", *map(str, args)], env=env, capture_output=True,
                          text=True, **kw)


def test_an_update_after_one_new_day_reads_only_the_new_files(calibrated, tmp_path, monkeypatch):
    c = calibrated
    work = tmp_path / "plant"
    shutil.copytree(c["folder"], work)
    _age(work)
    env = {**c["env"], "HELIOTWIN_CACHE_DIR": str(tmp_path / "cache")}
    first = _run(["update", "--scenario", c["scenario"], "--paint", work, "-o", tmp_path / "b0.h5", "--json",
                  tmp_path / "b0.json"], env)
    assert first.returncode == 0, first.stderr
    r0 = json.loads((tmp_path / "b0.json").read_text())
    assert r0["overall"]["records"] == 0  # nothing new yet: the plant saw every record
    assert r0["threshold"]["source"].startswith("stored by calibrate")  # not recomputed here
    moved = [(os.path.join(work, os.path.relpath(d, c["folder"])), s) for d, s in c["moved"]]
    _grow(moved, c["tail"], os.path.join(work, "metadata", "calibration-metadata.csv"))
    second = _run(["update", "--scenario", tmp_path / "b0.h5", "--paint", work, "-o", tmp_path / "b1.h5", "--json",
                   tmp_path / "b1.json"], env)
    assert second.returncode == 0, second.stderr
    r1 = json.loads((tmp_path / "b1.json").read_text())
    assert r1["reading"]["parsed"] == len(moved)  # today's files only, counted
    # every listed file is parsed now, taken from the index, or left out by id before it is even stat'ed
    assert r1["reading"]["parsed"] + r1["reading"]["indexed"] + r1["reading"]["skipped"] == r1["reading"]["files"]
    assert r1["overall"]["records"] == len(moved)
    # the first update needed the seen records (the state's time); from the second on they are left out unread
    assert r0["reading"]["skipped"] == 0 and r1["reading"]["skipped"] == r1["reading"]["files"] - len(moved)
    assert r1["counts"]["seen"] == r1["reading"]["skipped"]
    # ... and the update is the one that reads them all (given records are never left out); the records it
    # left out unlisted keep their index entries: reading the whole folder parses nothing
    b0 = load_scenario(tmp_path / "b0.h5")
    monkeypatch.setenv("HELIOTWIN_CACHE_DIR", env["HELIOTWIN_CACHE_DIR"])
    whole = P.load_paint_on_plant(work, b0.plant, cache=True)
    assert whole.reading["parsed"] == 0 and whole.reading["indexed"] == r1["reading"]["files"]
    every = update(b0, whole.records).scenario.learned["calibration"]
    mine = load_scenario(tmp_path / "b1.h5").learned["calibration"]
    assert np.allclose(every["deviations"], mine["deviations"], rtol=0, atol=1e-12)
    assert np.allclose(every["posterior"]["covariance"], mine["posterior"]["covariance"], rtol=0, atol=1e-18)


def test_a_killed_update_leaves_the_plant_and_the_index_intact(calibrated, tmp_path):
    c = calibrated
    plant_file = tmp_path / "plant.h5"
    shutil.copy(c["scenario"], plant_file)
    before = plant_file.read_bytes()
    env = {**c["env"], "HELIOTWIN_CACHE_DIR": str(tmp_path / "cache")}
    proc = subprocess.Popen([sys.executable, "-m", "heliotwin", "update", "--scenario", str(plant_file), "--paint",
                             str(c["folder"]), "-o", str(plant_file), "--in-place", "--quiet"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(1.0)  # somewhere inside the command (imports, reading or the update): the outcome is the same
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert plant_file.read_bytes() == before
    assert [f.name for f in tmp_path.iterdir() if f.name.startswith(".") or f.suffix == ".tmp"] == []
    again = _run(["update", "--scenario", plant_file, "--paint", c["folder"], "-o", plant_file, "--in-place",
                  "--json", tmp_path / "u.json"], env)
    assert again.returncode == 0, again.stderr
    assert json.loads((tmp_path / "u.json").read_text())["counts"]["records"] > 0


def test_two_concurrent_updates_of_one_plant_do_not_lose_one(calibrated, tmp_path):
    from heliotwin.io.lock import plant_lock

    c = calibrated
    plant_file = tmp_path / "plant.h5"
    shutil.copy(c["scenario"], plant_file)
    with plant_lock(plant_file):  # another update holds the plant
        busy = _run(["update", "--scenario", plant_file, "--paint", c["folder"], "-o", plant_file, "--in-place"],
                    c["env"])
    assert busy.returncode != 0 and "another heliotwin command is updating" in busy.stderr
    assert len(busy.stderr.strip().splitlines()) == 1


def test_in_place_needs_the_flag(calibrated, capsys):
    c = calibrated
    code, _, err = run_cli(capsys, "update", "--scenario", c["scenario"], "--paint", c["folder"], "-o", c["scenario"])
    assert_one_line_error(code, err, "--in-place")


def test_daily_updates_plans_and_aims_in_one_step_and_flags_an_alarm(calibrated, tmp_path):
    c = calibrated
    work = tmp_path / "plant"
    shutil.copytree(c["folder"], work)
    moved = [(os.path.join(work, os.path.relpath(d, c["folder"])), s) for d, s in c["moved"]]
    _grow(moved, c["tail"], os.path.join(work, "metadata", "calibration-metadata.csv"))
    stepped, _ = moved[0]  # one heliostat jumps: its new record is far off (a step of its axis-1 offset)
    data = json.loads(open(stepped).read())
    data["motor_position"]["axis_1_motor_position"] += 3000
    with open(stepped, "w") as fh:
        json.dump(data, fh)
    hid = os.path.basename(os.path.dirname(os.path.dirname(stepped)))
    plant_file = tmp_path / "plant.h5"
    shutil.copy(c["scenario"], plant_file)
    before = load_scenario(plant_file)
    env = {**c["env"], "HELIOTWIN_CACHE_DIR": str(tmp_path / "cache")}
    run = _run(["daily", "--plant", plant_file, "--paint", work, "--json", tmp_path / "d.json", "--day", "2024-06-21",
                "--slots", 3, "--peak-limit", 300000], env)
    assert run.returncode == 3, run.stderr  # written, and a step alarm needs a person
    report = json.loads((tmp_path / "d.json").read_text())
    assert [a["heliostat"] for a in report["update"]["alarms"]] == [hid]
    assert report["plan"]["proposals"][0]["heliostat"] == hid and len(report["plan"]["proposals"]) == 3
    assert report["plan"]["proposals"][0]["spread_after_mrad"] < report["plan"]["proposals"][0]["spread_now_mrad"]
    assert report["aimpoints"]["instants"][0]["peak_flux_w_m2"] <= 300000 * (1 + 1e-6)
    after = load_scenario(plant_file)
    assert len(after.provenance) == len(before.provenance) + 1 and after.provenance[-1]["step"] == "daily"
    assert sum(len(v) for v in after.provenance[-1]["records"].values()) == report["update"]["overall"]["records"]
    assert "aimpoints" in after.learned and "step alarm" in run.stdout


def test_default_threads_take_the_cores_others_leave_idle():
    from heliotwin.cli.common import default_threads, share_of_cores

    assert share_of_cores(2, 0.05) == 2  # idle: every core
    assert share_of_cores(2, 1.0) == 1 and share_of_cores(2, 5.0) == 1  # one busy process or more: one thread
    assert share_of_cores(16, 4.2) == 12 and share_of_cores(4, float("nan")) == 4
    env = {"OMP_NUM_THREADS": "3"}
    assert default_threads(env) is None and env == {"OMP_NUM_THREADS": "3"}  # the user's choice stands
    env = {"HELIOTWIN_THREADS": "5"}
    assert default_threads(env) == 5 and env["OMP_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "5"
    env = {}
    n = default_threads(env)
    assert 1 <= n <= os.cpu_count() and env["OMP_NUM_THREADS"] == str(n)


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="the kernel's runnable count is Linux's")
def test_busy_cores_see_a_busy_process_now_not_the_minute_before(tmp_path):
    """The load average trails by a minute: a command started after another one ended took one thread on an idle
    machine. busy_cores reads the runnable count now: a busy process is seen, a finished one is not."""
    from heliotwin.cli.common import busy_cores

    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        deadline = 200
        while deadline and busy.poll() is None and busy_cores() < 1.0:  # until the child is scheduled
            deadline -= 1
        assert busy_cores() >= 1.0
    finally:
        busy.kill()
        busy.wait()
    fake = tmp_path / "stat"
    fake.write_text("cpu  1 2 3 4\nprocs_running 1\nprocs_blocked 0\n")  # only the reader itself runs
    assert busy_cores(str(fake)) == 0.0
    fake.write_text("cpu  1 2 3 4\nprocs_running 4\n")
    assert busy_cores(str(fake)) == 3.0


def test_an_update_counts_what_it_does_not_assimilate(calibrated, tmp_path):
    """Records of a heliostat the plant does not know, and records the reader drops (motor steps out of range, a
    date in the future, an absurd sun azimuth), are counted and named in the report, never silently lost."""
    c = calibrated
    work = tmp_path / "plant"
    shutil.copytree(c["folder"], work)
    known = P.list_heliostats(work)[0]
    stranger = "ZZ99"
    shutil.copytree(work / known, work / stranger)
    os.rename(work / stranger / "Properties" / f"{known}-heliostat-properties.json",
              work / stranger / "Properties" / f"{stranger}-heliostat-properties.json")
    n_stranger = len([f for f in os.listdir(work / stranger / "Calibration") if f.endswith(P.RECORD_SUFFIX)])
    for f in os.listdir(work / stranger / "Calibration"):  # its own record ids
        os.rename(work / stranger / "Calibration" / f, work / stranger / "Calibration" / f"9{f}")
    moved = [(os.path.join(work, os.path.relpath(d, c["folder"])), s) for d, s in c["moved"]]
    _grow(moved, c["tail"], os.path.join(work, "metadata", "calibration-metadata.csv"))
    old = sorted(f for f in os.listdir(work / known / "Calibration") if f.endswith(P.RECORD_SUFFIX))[0]
    bad, bad_az = moved[0][0], os.path.join(work, known, "Calibration", old)
    data = json.loads(open(bad).read())
    data["motor_position"]["axis_1_motor_position"] = 1e9
    open(bad, "w").write(json.dumps(data))
    data = json.loads(open(bad_az).read())
    data["sun_azimuth"] = 1e300
    open(bad_az, "w").write(json.dumps(data))
    env = {**c["env"], "HELIOTWIN_CACHE_DIR": str(tmp_path / "cache")}
    run = _run(["update", "--scenario", c["scenario"], "--paint", work, "-o", tmp_path / "b.h5", "--json",
                tmp_path / "b.json"], env)
    assert run.returncode == 0, run.stderr
    counts = json.loads((tmp_path / "b.json").read_text())["counts"]
    assert counts["unknown_heliostats"] == 1 and counts["unknown_heliostat_records"] == n_stranger
    assert counts["unknown_heliostat_ids"] == [stranger]
    reasons = " ".join(counts["dropped_by_reason"])
    assert counts["dropped"] >= 2 and "motor steps axis 1" in reasons and "sun_azimuth" in reasons
    assert "this plant does not know" in run.stdout and "dropped by the reader" in run.stdout


def test_an_update_reads_a_folder_holding_some_of_the_plants_heliostats(calibrated, tmp_path):
    c = calibrated
    work = tmp_path / "plant"
    shutil.copytree(c["folder"], work)
    gone = P.list_heliostats(work)[0]
    shutil.rmtree(work / gone)
    env = {**c["env"], "HELIOTWIN_CACHE_DIR": str(tmp_path / "cache")}
    run = _run(["update", "--scenario", c["scenario"], "--paint", work, "-o", tmp_path / "b.h5", "--json",
                tmp_path / "b.json"], env)
    assert run.returncode == 0, run.stderr
    report = json.loads((tmp_path / "b.json").read_text())
    assert report["counts"]["records"] == sum(len(P.load_paint(work, [h]).records) for h in P.list_heliostats(work))
