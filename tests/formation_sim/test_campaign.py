"""formation-campaign: strict file validation, identical results however the runs are spread, resuming."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml

from formation_sim.cli import campaign, campaign_file, campaign_results
from formation_sim.cli.campaign import run_campaign
from formation_sim.cli.campaign_file import load_campaign

#: two samples of the paper's formation, 30 ms each, at two rates: 4 runs of ~0.1 s
SMALL = {
    "formation": "paper.yaml",
    "samples": 2,
    "seed": 7,
    "control_rates": [2000, 10000],
    "duration": 0.03,
    "vary": {"mass": [0.8, 1.2], "inertia": [0.8, 1.2], "disturbance_amplitude": [0, 0.1], "initial_rotation": 0.05},
}


def write_campaign(tmp_path: Path, paper_path: Path, doc: dict) -> Path:
    (tmp_path / "paper.yaml").write_text(paper_path.read_text())
    path = tmp_path / "campaign.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def results(out: Path) -> list[dict]:
    """runs.csv without the wall time (the only column that may differ between runs)."""
    import csv

    with (out / "runs.csv").open() as f:
        return [{k: v for k, v in row.items() if k != "wall_time"} for row in csv.DictReader(f)]


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"samples": 0}, "samples"),
        ({"samples": "ten"}, "samples"),
        ({"control_rates": []}, "control_rates"),
        ({"control_rates": [1000, -5]}, r"control_rates\[1\]"),
        ({"vary": {"mass": [1.2, 0.8]}}, r"vary\.mass"),
        ({"vary": {"masss": [0.8, 1.2]}}, r"vary\.masss"),
        ({"vary": {"initial_rotation": 4.0}}, r"vary\.initial_rotation"),
        ({"formation": "missing.yaml"}, "formation"),
        ({"sedd": 1}, "sedd"),
    ],
)
def test_bad_campaign_file_exits_2_naming_the_field(tmp_path, paper_path, capsys, change, field) -> None:
    """Every invalid field is refused before anything runs, with its name in the message."""
    path = write_campaign(tmp_path, paper_path, {**SMALL, **change})
    assert campaign.main([str(path), "--out", str(tmp_path / "out")]) == 2
    assert re.search(rf"formation-campaign: {field}: ", capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_same_results_with_1_worker_2_workers_and_a_dask_cluster(tmp_path, paper_path) -> None:
    """Per-sample seeds: the table is identical whether the runs go to 1 or 2 local processes or to Dask."""
    from distributed import LocalCluster

    c = load_campaign(write_campaign(tmp_path, paper_path, SMALL))
    run_campaign(c, tmp_path / "one", workers=1, quiet=True)
    run_campaign(c, tmp_path / "two", workers=2, quiet=True)
    loopback = {"host": "127.0.0.1", "dashboard_address": None}  # nothing leaves the machine
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, **loopback) as cluster:
        run_campaign(c, tmp_path / "dask", scheduler=cluster.scheduler_address, quiet=True)
    one = results(tmp_path / "one")
    assert len(one) == 4 and {r["control_rate"] for r in one} == {"2000.0", "10000.0"}
    assert len({(r["peak_force"]) for r in one}) == 4  # every run has its own plant or rate
    assert results(tmp_path / "two") == one
    assert results(tmp_path / "dask") == one
    summary = json.loads((tmp_path / "one" / "summary.json").read_text())
    assert set(summary["per_control_rate"]) == {"2000", "10000"}
    assert (tmp_path / "one" / "pass_rate.png").stat().st_size > 5000


def test_an_interrupted_campaign_resumes_without_rerunning(tmp_path, paper_path, monkeypatch) -> None:
    """Runs already in runs.jsonl are not run again; a torn last line (a killed writer) is run again."""
    c = load_campaign(write_campaign(tmp_path, paper_path, SMALL))
    out = tmp_path / "out"
    run_campaign(c, out, workers=1, quiet=True)
    full = results(out)
    lines = (out / "runs.jsonl").read_text().splitlines()
    (out / "runs.jsonl").write_text("\n".join(lines[:2]) + "\n" + lines[2][:20])  # 2 done, 1 torn
    ran = []
    real = campaign.run_task
    monkeypatch.setattr(campaign, "run_task", lambda task: ran.append(task.key) or real(task))
    run_campaign(c, out, workers=1, quiet=True)
    done_before = {(json.loads(x)["sample"], json.loads(x)["control_rate"]) for x in lines[:2]}
    assert len(ran) == 2 and not done_before & set(ran)
    assert results(out) == full


def test_wilson_interval_contains_a_0_and_a_100_percent_rate_exactly() -> None:
    """Every k of n, n up to 300, lies in its interval; all passes end at 1.0 exactly, none start at 0.0."""
    for n in range(1, 301):
        for k in range(n + 1):
            lo, hi = campaign_results.wilson(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0, (k, n, lo, hi)
        assert campaign_results.wilson(n, n)[1] == 1.0 and campaign_results.wilson(0, n)[0] == 0.0
    assert campaign_results.wilson(0, 0) == (0.0, 1.0)


def _fake_run(task: campaign.Task) -> dict:
    """A row of runs.csv without running: every run at 10 kHz passes, every run below fails."""
    passed = task.control_rate >= 10000
    return {
        "sample": task.sample,
        "control_rate": task.control_rate,
        "seed": "0",
        "verdict": "PASS" if passed else "FAIL",
        "violation_t": None if passed else 0.01,
        "violation_kind": None if passed else "edge",
        "violation_where": None if passed else "1-2",
        "violation_channel": None if passed else "e",
        "worst_margin_e": 0.5 if passed else -0.1,
        "worst_margin_psi": 0.6,
        "worst_margin_v": 0.7,
        "peak_force": 1.0,
        "peak_torque": 1.0,
        "wall_time": 0.0,
    }


def test_all_pass_and_all_fail_rates_give_a_summary_and_figures_also_on_resume(
    tmp_path, paper_path, monkeypatch, capsys
) -> None:
    """4/4 passes at 10 kHz and 0/4 at 2 kHz: exit 0, intervals [lo, 1] and [0, hi], both figures; again on resume."""
    path = write_campaign(tmp_path, paper_path, {**SMALL, "samples": 4})
    monkeypatch.setattr(campaign, "run_task", _fake_run)
    out = tmp_path / "out"
    for _ in range(2):  # the second call resumes: nothing left to run, the results written again
        assert campaign.main([str(path), "--out", str(out), "--workers", "1", "--quiet"]) == 0
        per = json.loads((out / "summary.json").read_text())["per_control_rate"]
        assert per["10000"]["pass_rate"] == 1.0 and per["10000"]["pass_rate_ci95"][1] == 1.0
        assert per["2000"]["pass_rate"] == 0.0 and per["2000"]["pass_rate_ci95"][0] == 0.0
        assert (out / "pass_rate.png").stat().st_size > 5000 and (out / "worst_margin.png").stat().st_size > 5000
    assert "4/4 pass" in capsys.readouterr().out


def test_a_crash_exits_4_not_1(tmp_path, paper_path, monkeypatch, capsys) -> None:
    """An internal error during the runs is INCOMPLETE (exit 4), never 1, which means a funnel was left."""

    def crash(task: campaign.Task) -> dict:
        raise RuntimeError("boom")

    path = write_campaign(tmp_path, paper_path, SMALL)
    monkeypatch.setattr(campaign, "run_task", crash)
    assert campaign.main([str(path), "--out", str(tmp_path / "out"), "--workers", "1", "--quiet"]) == 4
    assert "formation-campaign: INCOMPLETE: internal error" in capsys.readouterr().err


REPO = Path(__file__).resolve().parents[2]


def test_docs_reference_matches_the_declaration() -> None:
    """docs/campaigns.md holds the table `formation-campaign --schema` prints, verbatim."""
    doc = (REPO / "docs" / "campaigns.md").read_text(encoding="utf-8")
    assert campaign_file.reference_markdown() in doc, "regenerate: formation-campaign --schema (see docs/campaigns.md)"


def test_schema_option_prints_the_reference(capsys) -> None:
    """formation-campaign --schema prints the reference table and exits 0."""
    assert campaign.main(["--schema"]) == 0
    assert capsys.readouterr().out == campaign_file.reference_markdown()


def test_a_campaign_has_exactly_the_declared_keys() -> None:
    """Campaign's attributes are CAMPAIGN_KEYS in order: the record the declaration's parser builds."""
    import dataclasses

    assert [f.name for f in dataclasses.fields(campaign_file.Campaign)] == [k.name for k in campaign_file.CAMPAIGN_KEYS]


def test_every_declared_key_is_read_and_no_other(tmp_path, paper_path) -> None:
    """A file with every declared key (the preset plus a duration) loads with each value; one more key
    at the top or in vary is refused."""
    doc = yaml.safe_load((REPO / "config" / "campaigns" / "paper_random_plants.yaml").read_text(encoding="utf-8"))
    links = {
        "apply_to": ["poses", "wrench"],
        "delay": [0.0, 0.001],
        "loss": [0.0],
        "jitter": [0.0],
        "sensor_rate": [None],
    }
    doc.update(formation="paper.yaml", duration=0.5, links=links, gains={"delta": [0.1], "gamma": [15.0, 10.0]})
    declared = {k.name: {c.name for c in k.children} for k in campaign_file.CAMPAIGN_KEYS}
    assert set(doc) == set(declared) and set(doc["vary"]) == declared["vary"]
    assert set(doc["links"]) == declared["links"] and set(doc["gains"]) == declared["gains"]
    c = load_campaign(write_campaign(tmp_path, paper_path, doc))
    assert (c.samples, c.seed, c.control_rates, c.duration) == (100, 2026, (1000.0, 2000.0, 5000.0, 10000.0), 0.5)
    assert c.vary == {
        "mass": (0.5, 1.5),
        "inertia": (0.5, 1.5),
        "disturbance_amplitude": (0.0, 0.1),
        "noise_amplitude": (0.0, 0.1),
        "initial_rotation": 0.05,
    }
    assert c.links == {
        "apply_to": ("poses", "wrench"), "delay": (0.0, 0.001), "loss": (0.0,), "jitter": (0.0,), "sensor_rate": (None,)
    }  # fmt: skip
    assert c.gains == {"delta": (0.1,), "gamma": (15.0, 10.0)} and len(c.conditions()) == 4
    for extra in ({"extra": 1}, {"vary": {**doc["vary"], "extra": [0, 1]}}):
        with pytest.raises(campaign_file.CampaignError, match="extra: unknown key"):
            load_campaign(write_campaign(tmp_path, paper_path, {**doc, **extra}))


def test_defaults_are_the_declared_ones(tmp_path, paper_path) -> None:
    """Without its optional keys a campaign has the declared defaults: the file's duration, nothing varied."""
    required = {k.name for k in campaign_file.CAMPAIGN_KEYS if k.default is campaign_file.REQUIRED}
    assert required == {"formation", "samples", "seed", "control_rates"}
    c = load_campaign(write_campaign(tmp_path, paper_path, {k: v for k, v in SMALL.items() if k in required}))
    assert (c.duration, c.vary) == (None, {})


@pytest.mark.parametrize("path", sorted((REPO / "config" / "campaigns").glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_campaign_files_are_valid(path: Path) -> None:
    """Every campaign file in config/campaigns/ loads."""
    assert load_campaign(path).samples > 0


def test_docs_name_every_column_of_runs_csv() -> None:
    """docs/campaigns.md names every column of runs.csv and every file a campaign writes."""
    doc = (REPO / "docs" / "campaigns.md").read_text(encoding="utf-8")
    names = [*campaign_results.COLUMNS, "runs.jsonl", "runs.csv", "summary.json", "pass_rate.png", "worst_margin.png"]
    assert [name for name in names if f"`{name}`" not in doc] == []


def test_a_link_grid_gives_a_pass_rate_per_condition_and_the_largest_delay_and_loss(tmp_path, paper_path) -> None:
    """links: delay × loss crossed with the rate: a row per sample, rate and condition (its values named), a
    pass rate per condition, the largest delay and loss at which the runs pass, link_pass_rate.png; a
    rerun resumes by condition too (nothing left to do)."""
    doc = {**SMALL, "control_rates": [10000], "links": {"delay": [0.0, 0.0005], "loss": [0.0, 0.5]}}
    c = load_campaign(write_campaign(tmp_path, paper_path, doc))
    out = tmp_path / "out"
    summary = run_campaign(c, out, workers=1, quiet=True)
    rows = (out / "runs.csv").read_text().splitlines()
    assert rows[0].split(",")[:8] == ["sample", "control_rate", *campaign_file.CONDITIONS]
    assert len(rows) == 1 + 2 * 4
    cells = {(x["link_delay"], x["link_loss"]): x for x in summary["per_condition"]}
    assert set(cells) == {(0.0, 0.0), (0.0, 0.5), (0.0005, 0.0), (0.0005, 0.5)}
    assert all(x["runs"] == 2 for x in cells.values())
    # 30 ms of the paper: too short for half a millisecond or half the samples lost to show (the
    # rule of the largest delay and loss when a cell fails: the test below)
    assert all(x["pass_rate"] == 1.0 for x in cells.values())
    (tol,) = summary["tolerance"]
    assert (tol["largest_delay"], tol["largest_loss"]) == (0.0005, 0.5)
    assert (out / "link_pass_rate.png").stat().st_size > 5_000
    assert json.loads((out / "summary.json").read_text())["tolerance"] == summary["tolerance"]
    assert campaign.tasks(c) and all(t.key in campaign._finished(out / "runs.jsonl") for t in campaign.tasks(c))


def test_a_sensor_faster_than_a_control_rate_is_refused(tmp_path, paper_path) -> None:
    doc = {**SMALL, "links": {"sensor_rate": [None, 1e6]}}
    with pytest.raises(campaign_file.CampaignError, match=r"links\.sensor_rate\[1\]: .* faster than the control rate"):
        load_campaign(write_campaign(tmp_path, paper_path, doc))


def test_the_largest_delay_is_the_last_of_an_unbroken_run_of_passes() -> None:
    """A cell under 95 % ends the run: a pass at a larger delay after it does not count."""

    def cell(delay: float, loss: float, rate: float) -> dict:
        return {"control_rate": 1000.0, "link_delay": delay, "link_loss": loss, "link_jitter": 0.0,
                "sensor_rate": None, "delta": None, "gamma": None, "pass_rate": rate}  # fmt: skip

    cells = [cell(0.0, 0.0, 1.0), cell(0.001, 0.0, 0.96), cell(0.002, 0.0, 0.5), cell(0.005, 0.0, 1.0)]
    cells += [cell(0.0, 0.01, 0.97), cell(0.0, 0.05, 0.2)]
    (tol,) = campaign_results.tolerance(cells)
    assert (tol["largest_delay"], tol["largest_loss"]) == (0.001, 0.01)
    (none,) = campaign_results.tolerance([cell(0.0, 0.0, 0.9), cell(0.001, 0.0, 1.0)])
    assert none["largest_delay"] is None
