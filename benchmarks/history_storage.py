"""What the hospital's history costs on disk, per bed and day, and how fast a minute of a hospital is written.

    python benchmarks/history_storage.py          # writes benchmarks/history_storage.md (about a minute)

A throw-away PostgreSQL (the server the tests start, ``tests/postgres_server.py``, here with fsync on) with the
history's tables (``appliance.hospital.history``). Pressure: a day of summaries at 1 Hz for ``--beds`` beds,
through ``MinuteTrend`` into one row per bed and minute written as the writer writes them (each minute's rows
in one transaction once the minute is over): occupied beds with four regions (occiput, sacrum, both heels) and
empty beds with none. Events: ``--events`` alarm events in the record's full shape (``Event.to_dict`` with bed
and number). Sizes are ``pg_total_relation_size`` of the partitions (table, TOAST and indexes) plus, for
events, the key table, after ``VACUUM``. Time: ``--repeats`` writes of one minute of ``--hospital`` beds in one
transaction, the median set against the minute it has to be written in.
"""

from __future__ import annotations

import argparse
import datetime as dt
import statistics
import sys
import time
from pathlib import Path

import psycopg

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))
from postgres_server import running_postgres  # noqa: E402
from report import machine, table  # noqa: E402

from appliance.alerts.events import Event  # noqa: E402
from appliance.hospital.history.schema import EVENTS, PRESSURE, create_schema, partitions  # noqa: E402
from appliance.hospital.history.store import StoredEvent, write_events, write_minutes  # noqa: E402
from appliance.hospital.history.trend import MinuteTrend  # noqa: E402

DAY = dt.datetime(2026, 11, 26, tzinfo=dt.UTC)
ZONES = ("occiput", "sacrum", "heel-left", "heel-right")


def summary(second: int, occupied: bool) -> dict:
    """A bed's summary as ``ward_summary`` makes it, with pressures that move through the day."""
    if not occupied:
        return {"peak_mmhg": None, "posture": None, "regions": []}
    wave = (second % 7200) / 7200
    return {"peak_mmhg": 35.0 + 30 * wave, "posture": "supine",
            "regions": [{"zone": zone, "words": zone, "peak_mmhg": 20.0 + 10 * i + 30 * wave,
                         "dose": round(wave * (i + 1) / 4, 4)} for i, zone in enumerate(ZONES)]}


def bed_day(db, beds: int, occupied: bool) -> int:
    """Write a day of minutes for ``beds`` beds; the pressure partitions' bytes."""
    db.execute("TRUNCATE pressure_minute")
    start = DAY.timestamp()
    for minute in range(1440):
        trend = MinuteTrend()
        for bed in range(beds):
            for second in range(60):
                t = minute * 60 + second
                trend.add("ward1", f"bed{bed:04d}", start + t + 0.5, summary(t, occupied))
        write_minutes(db, trend.take())
    return relation_bytes(db, partitions(db, PRESSURE))


def relation_bytes(db, names: list[str]) -> int:
    db.commit()
    db.autocommit = True
    for name in names:
        db.execute(f'VACUUM ANALYZE "{name}"')
    db.autocommit = False
    return sum(db.execute("SELECT pg_total_relation_size(%s)", (name,)).fetchone()[0] for name in names)


def event_bytes(db, count: int) -> float:
    rows = []
    for seq in range(1, count + 1):
        body = Event(1_800_000_000.0 + seq, "alarm", "raised", "high", "pressure", "pressure:sacrum", "sacrum",
                     "supine", 450.0, 1100.0, seq, "sacrum: pressure above the tissue's tolerance for 120 min",
                     None, None, "P-000123").to_dict()
        rows.append(StoredEvent(DAY + dt.timedelta(seconds=seq), "ward1", f"bed{seq % 30:04d}", seq, "alarm",
                                {**body, "bed_id": f"bed{seq % 30:04d}", "seq": seq}))
    write_events(db, rows)
    return relation_bytes(db, [*partitions(db, EVENTS), "event_key"]) / count


def minute_write_s(db, beds: int, repeats: int) -> float:
    times = []
    for repeat in range(repeats):
        trend = MinuteTrend()
        at = (DAY + dt.timedelta(days=1, minutes=repeat)).timestamp()
        for bed in range(beds):
            for second in range(60):
                trend.add("ward1", f"bed{bed:04d}", at + second, summary(second, True))
        minutes = trend.take()
        started = time.perf_counter()
        write_minutes(db, minutes)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--beds", type=int, default=10, help="beds whose day is written (default 10)")
    parser.add_argument("--events", type=int, default=10000, help="events written (default 10000)")
    parser.add_argument("--hospital", type=int, default=3000, help="beds in the minute timed (default 3000)")
    parser.add_argument("--repeats", type=int, default=5, help="minutes timed (default 5)")
    parser.add_argument("--out", type=Path, default=HERE / "history_storage.md", help="the report")
    args = parser.parse_args(argv)
    with running_postgres(fsync=True) as server:
        server.psql("CREATE DATABASE bench")
        with psycopg.connect(server.dsn("bench")) as db:
            create_schema(db)
            version = db.execute("SHOW server_version").fetchone()[0]
            occupied = bed_day(db, args.beds, True) / args.beds
            empty = bed_day(db, args.beds, False) / args.beds
            per_event = event_bytes(db, args.events)
            db.execute("TRUNCATE pressure_minute")
            write_s = minute_write_s(db, args.hospital, args.repeats)
    kb = 1024
    rows = [["pressure, occupied bed (4 regions)", f"{occupied / kb:.0f} KiB", f"{occupied / 1440:.0f} B",
             f"{occupied * args.hospital / kb ** 3:.2f} GiB", f"{occupied * args.hospital * 90 / kb ** 3:.0f} GiB"],
            ["pressure, empty bed", f"{empty / kb:.0f} KiB", f"{empty / 1440:.0f} B",
             f"{empty * args.hospital / kb ** 3:.2f} GiB", f"{empty * args.hospital * 90 / kb ** 3:.0f} GiB"]]
    text = "\n".join([
        "# History storage: per bed and day",
        "",
        "`python benchmarks/history_storage.py` (see its docstring for the method). "
        f"{args.beds} beds' days of 1 Hz summaries down-sampled to 1,440 minutes each; "
        f"{args.events} events; PostgreSQL {version} with fsync on.",
        "",
        table(["kind", "per bed-day", "per row", f"{args.hospital} beds a day", f"{args.hospital} beds, 90 days"],
              rows),
        "",
        f"Events: {per_event:.0f} bytes each, table, indexes and key together; at one event per bed every "
        f"2 hours that is {per_event * 12 / kb:.1f} KiB per bed-day.",
        "",
        f"Writing one minute of {args.hospital} beds ({args.hospital} rows, one transaction): median "
        f"{write_s:.3f} s of the 60 s it has, over {args.repeats} minutes ({60 / write_s:.0f} times faster than "
        "needed).",
        "",
        f"Machine: {machine()}.",
        ""])
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
