"""A fleet of three boats flying one PASST loop (passt_mav.vehicle.fleet_controller) against vehicle_sim.

``vehicle-sim --boats 3`` (:class:`vehicle_sim.fleet.Fleet`: one field, one clock, system
ids 1-3, started in different cells of the wave field of test_controller) served on
loopback TCP; the controller talks to each boat over its own link, as ``passt-mav run``
does with ``vehicles:``. A boat that goes silent for good is simulated with three
separate in-process simulators (one of them stopped mid-leg).
"""

from __future__ import annotations

import contextlib

import pytest
from mavlink_helpers import inprocess_factory, link_config, vehicle
from test_controller import mission, sim_config, wave_field

from passt_mav.analysis.html_page import pyplot
from passt_mav.commands.run import LEAN_STREAMS
from passt_mav.mavlink import Link
from passt_mav.runs.rundir import RunDir
from passt_mav.runs.store import SampleStore
from passt_mav.vehicle.controller import build_predictor
from passt_mav.vehicle.fleet_controller import FleetController
from vehicle_sim import Simulator

SPEEDUP = 20.0  # three simulators and three boat threads share the GIL: slower than one boat's 50x
STARTS = [(1, 1), (6, 6), (1, 6)]


@contextlib.contextmanager
def fleet_on_loopback(field, starts=STARTS, tlogs=None):
    """``vehicle-sim --boats 3`` in-process, each boat on an OS-chosen loopback TCP port; links to each
    (writing ``tlogs[k]`` when given)."""
    from vehicle_sim.fleet import Fleet

    latlon = [tuple(float(x) for x in field.grid.cell_to_latlon(r, c)) for r, c in starts]
    fleet = Fleet(field, starts=latlon, config=sim_config())
    fleet.serve(["tcp:127.0.0.1:0"], speedup=SPEEDUP)
    links = []
    try:
        for k, port in enumerate(fleet.tcp_ports()):
            links.append(
                Link(
                    link_config(
                        connect=f"tcp:127.0.0.1:{port}",
                        stream_rates_hz=LEAN_STREAMS,
                        timeout_s=0.5,
                        link_lost_s=1.0,
                        tlog=None if tlogs is None else str(tlogs[k]),
                    )
                ).connect()
            )
        yield fleet, links
    finally:
        for link in links:
            link.close()
        fleet.stop()


@contextlib.contextmanager
def fleet_served(field, starts=STARTS):
    sims, links = [], []
    try:
        for k, (r, c) in enumerate(starts):
            lat, lon = field.grid.cell_to_latlon(r, c)
            sim = Simulator(field, home=(float(lat), float(lon)), config=sim_config().replace(sysid=k + 1))
            link = Link(
                link_config(stream_rates_hz=LEAN_STREAMS, timeout_s=0.5, link_lost_s=1.0),
                connection_factory=inprocess_factory(sim),
            )
            sim.serve([], speedup=SPEEDUP)
            sims.append(sim)
            links.append(link.connect())
        yield sims, links
    finally:
        for link in links:
            link.close()
        for sim in sims:
            sim.stop()


def fleet_mission(tmp_path, field, **over):
    vehicles = [
        {"connect": f"tcp:127.0.0.1:{5760 + 10 * k}", "speed_mps": 5.0, "wp_radius_m": 3.0, "start_cell": list(s)}
        for k, s in enumerate(STARTS)
    ]
    from passt_mav.mission.config import validate_mission

    data = {"vehicles": vehicles, "legs": 2}
    data.update(over)
    base = mission(tmp_path, field).model_dump(mode="json")
    base.pop("vehicle")
    base.update(data)
    return validate_mission(base, source="fleet test")


def run_fleet(tmp_path, field, cfg, links, **kw):
    pred, info = build_predictor(cfg.model, field, echo=lambda s: None)
    rd = RunDir(tmp_path / "run").create()
    fleet = FleetController(
        cfg,
        links,
        rd,
        field=field,
        predictor=pred,
        predictor_info=info,
        vehicles=[vehicle(x) for x in links],
        field_time_at_boot=0.0,
        speedup_hint=SPEEDUP,
        ready_timeout_s=20.0,
        pause_timeout_s=5.0,
        **kw,
    )
    return fleet, rd


def _overlap(a, b) -> bool:
    return a["t_start"] < b["t_end"] and b["t_start"] < a["t_end"]


def test_three_boats_fly_one_loop_with_disjoint_paths_and_one_store(tmp_path):
    field = wave_field()
    cfg = fleet_mission(tmp_path, field)
    with fleet_on_loopback(field) as (_sim, links):
        fleet, rd = run_fleet(tmp_path, field, cfg, links)
        summary = fleet.run()
    assert summary["status"] == "complete", summary["events"]
    assert [b["status"] for b in summary["boats"]] == ["complete"] * 3
    assert sorted(b["sysid"] for b in summary["boats"]) == [1, 2, 3]
    # each boat ends loitering, armed (vehicle.on_end: loiter), never armed and drifting in HOLD
    assert [(b["end"]["mode"], b["end"]["armed"]) for b in summary["boats"]] == [("LOITER", True)] * 3
    legs = summary["legs"]
    assert len(legs) == 6 and sorted(x["index"] for x in legs) == list(range(6))
    assert sorted(x["boat"] for x in legs) == [0, 0, 1, 1, 2, 2]
    # every boat's samples reach the one store, keyed by its system id
    with SampleStore(rd.samples_db, readonly=True) as st:
        recs = st.all()
    by_src = {s: sum(1 for r in recs if r.source == s) for s in {r.source for r in recs}}
    assert set(by_src) == {"mav:1/1", "mav:2/1", "mav:3/1"} and min(by_src.values()) > 20, by_src
    for leg in legs:  # a leg's samples are its own boat's
        assert {r.source for r in recs if r.leg == leg["index"]} == {f"mav:{leg['sysid']}/1"}
        assert leg["n_samples"] > 5 and leg["rmse_passt"] is not None
    # no two boats are given the same cell while their legs overlap in time (start cells excepted:
    # a boat starts where it is)
    for a in legs:
        for b in legs:
            if a["boat"] < b["boat"] and _overlap(a, b):
                ca = {tuple(x) for x in a["path"][1:]}
                cb = {tuple(x) for x in b["path"][1:]}
                assert not ca & cb, (a["index"], b["index"], ca & cb)
    # one shared estimate: the field estimate after the last leg beats the model alone
    last = max(legs, key=lambda x: x["t_end"])
    assert last["rmse_passt"] < last["rmse_model"]


@pytest.mark.long(reason="three boats fly until one link's loss window runs out in vehicle time: ~30 s")
def test_a_boat_whose_link_dies_mid_leg_is_reported_and_the_others_complete(tmp_path):
    field = wave_field()
    cfg = fleet_mission(tmp_path, field)
    with fleet_served(field) as (sims, links):
        fleet, rd = run_fleet(tmp_path, field, cfg, links)
        killed = {}

        def kill_when_flying():
            import time

            while not killed:
                b = fleet.boats[1]
                if (
                    b.status == "flying"
                    and b.collector is not None
                    and b.collector.leg is not None
                    and fleet.store.count(b.collector.leg) >= 3
                ):
                    killed["leg"] = b.collector.leg
                    sims[1].stop()  # the boat's autopilot goes silent for good
                    return
                time.sleep(0.01)

        import threading

        t = threading.Thread(target=kill_when_flying, daemon=True)
        t.start()
        summary = fleet.run()
        t.join(1.0)
    assert killed, "boat 1 never got into a leg"
    status = {b["boat"]: b["status"] for b in summary["boats"]}
    assert status[0] == status[2] == "complete" and status[1] != "complete", status
    assert summary["status"] == "partial" and 1 in summary["lost_boats"]
    assert any("boat 1" in e and "dropped out" in e for e in summary["events"])
    # the live view's alert (events.jsonl, issue 29)
    from passt_mav.runs.live import read_events

    ev = read_events(rd.root)[0]
    assert any(e["kind"] == "boat_dropped" and e["boat"] == 1 and e["level"] == "alert" for e in ev), ev
    assert sum(1 for x in summary["legs"] if x["boat"] in (0, 2)) == 4
    # nothing stored is lost: the interrupted leg's samples are in the store
    with SampleStore(rd.samples_db, readonly=True) as st:
        assert st.count(killed["leg"]) >= 3


def test_a_boat_whose_link_drops_mid_leg_reconnects_and_the_fleet_completes(tmp_path):
    field = wave_field()
    cfg = fleet_mission(tmp_path, field)
    with fleet_on_loopback(field) as (sim, links):
        fleet, _rd = run_fleet(tmp_path, field, cfg, links)
        dropped = {}

        def drop_when_flying():
            import time

            while not dropped and fleet.status == "running":
                b = fleet.boats[2]
                if b.collector is not None and b.collector.leg is not None and fleet.store.count(b.collector.leg) >= 3:
                    dropped["leg"] = b.collector.leg
                    sim.drop_clients(2)  # the vehicle side closes boat 2's TCP link
                    return
                time.sleep(0.01)

        import threading

        t = threading.Thread(target=drop_when_flying, daemon=True)
        t.start()
        summary = fleet.run()
        t.join(1.0)
    assert dropped, "boat 2 never got into a leg"
    assert summary["status"] == "complete", summary["events"]
    assert [b["status"] for b in summary["boats"]] == ["complete"] * 3
    assert len(summary["legs"]) == 6
    assert any(e.startswith(f"boat 2: leg {dropped['leg'] + 1}: link lost") for e in summary["events"]), summary[
        "events"
    ]


def test_replay_of_a_fleet_run_reproduces_every_boats_paths_and_rmse(tmp_path):
    from passt_mav.analysis.replay import replay

    field = wave_field()
    cfg = fleet_mission(tmp_path, field)
    rd = RunDir(tmp_path / "run").create()
    with fleet_on_loopback(field, tlogs=[rd.boat_tlog(k) for k in range(3)]) as (_sim, links):
        fleet, rd = run_fleet(tmp_path, field, cfg, links)
        summary = fleet.run()
    assert summary["status"] == "complete", summary["events"]
    assert [p.name for p in rd.boat_tlogs()] == ["flight_boat0.tlog", "flight_boat1.tlog", "flight_boat2.tlog"]
    res = replay(rd.root, out=False)
    assert res.kind == "fleet" and res.reproduced is True, (res.notes, [x.notes for x in res.legs])
    assert [x.index for x in res.legs] == list(range(6))
    for got, want in zip(res.legs, sorted(summary["legs"], key=lambda r: r["index"])):
        assert got.path == want["path"] and got.notes[0] == f"boat {want['boat']}"
        assert got.rmse_passt == pytest.approx(want["rmse_passt"], abs=1e-6)
        assert got.rmse_model == pytest.approx(want["rmse_model"], abs=1e-6)


def test_report_of_a_fleet_run_draws_every_boats_track(tmp_path):
    from passt_mav.analysis import report

    field = wave_field()
    cfg = fleet_mission(tmp_path, field, legs=1)
    rd = RunDir(tmp_path / "run").create()
    with fleet_on_loopback(field, tlogs=[rd.boat_tlog(k) for k in range(3)]) as (_sim, links):
        fleet, rd = run_fleet(tmp_path, field, cfg, links)
        summary = fleet.run()
    assert summary["status"] == "complete"
    run = report.load_run(rd.root)
    assert sorted(run.boat_tracks) == [0, 1, 2]
    for k, (r, c) in enumerate(STARTS):  # each boat's track starts in its own start cell
        lat, lon = run.boat_tracks[k][0]
        assert tuple(int(x) for x in field.grid.latlon_to_cell(lat, lon, clip=True)) == (r, c)
    plt = pyplot()
    fig = report._fig_track(run, plt)
    labels = [ln.get_label() for ln in fig.axes[0].get_lines()]
    assert [x for x in labels if x.startswith("boat")] == ["boat 0, sysid 1", "boat 1, sysid 2", "boat 2, sysid 3"]
    plt.close(fig)
    html = report.write_report(rd.root).read_text()
    assert "one colour per boat" in html
