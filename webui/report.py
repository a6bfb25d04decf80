"""The shift report as files: a PDF for the bed's paper record and a CSV of the same events for a spreadsheet.

The PDF has who was in the bed (its admissions and discharges), what a
handover reads on the screen's shift summary (turns, the alarms and who
acknowledged them how fast, minutes at or above the threshold per region) and
a chart of the peak pressure at each site over the period; the CSV lists
every event the store logged in the period, one a row. Both come
from the store and the live view alone, so the screen and ``appliance report``
make the same files. Clock times are the site's time zone's (with its
abbreviation, so the hour repeated when the clocks go back reads apart); the
CSV gives each event in UTC and as the local time with its offset. PDFs are
written with fpdf2's built-in Helvetica, which holds Latin-1 only: other
characters are shown as "?".
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from zoneinfo import ZoneInfo

from flask import Blueprint, Response, abort
from fpdf import FPDF
from fpdf.enums import XPos, YPos

from appliance.alerts.anatomy import site_words
from appliance.alerts.wording import alarm_words
from appliance.store import Store
from appliance.time_zones import WALL_CLOCK_AFTER_S, clock_text, local_time, time_zone
from webui.alarms import reader
from webui.clocks import zone
from webui.history import (NO_HISTORY, History, ShiftSummary, duration, read_history, requested_hours, summarise,
                           threshold_mmhg)
from webui.live import snapshot

CSV_COLUMNS = ("time_utc", "time_local", "time_s", "type", "kind", "priority", "category", "key", "alarm", "site",
               "posture", "message", "user", "patient")
CHART_W_MM, CHART_H_MM = 180.0, 60.0
UTC_ZONE = time_zone("UTC")
SITE_COLOURS = ((31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (23, 190, 207),
                (140, 86, 75), (227, 119, 194))


@dataclass(frozen=True)
class ShiftReport:
    """One bed's period: its history and summary, every event logged in it, who was in the bed (see
    :func:`patient_words`), and the zone its clock times are written in."""

    bed_id: str
    patient: str
    history: History
    summary: ShiftSummary
    events: list[dict]
    zone: ZoneInfo

    def clock(self, time_s: float) -> str:
        return clock_text(time_s, self.zone)


def shift_report(s: Store, hours: float, live: dict, threshold: float, zone: ZoneInfo) -> ShiftReport | None:
    """The last ``hours`` of store ``s`` (None if it recorded nothing); ``live`` is the live view's snapshot;
    clock times in ``zone``."""
    history = read_history(s, hours)
    if history is None:
        return None
    episodes = [e for e in s.episodes() if e["time_s"] <= history.end_s]
    events = [e for e in s.events_since(history.start_s) if e["time_s"] <= history.end_s]
    return ShiftReport(live.get("bed_id") or "unknown", patient_words(episodes, history.start_s, live), history,
                       summarise(history, threshold), events, zone)


def patient_words(episodes: list[dict], start_s: float, live: dict) -> str:
    """Who was in the bed: the patient admitted at the period's end (named as the live view names them), and
    those discharged within it, so a report made after a discharge still says whose stay it covers.

    ``episodes`` are the store's admissions and discharges up to the period's end, oldest first.
    """
    earlier: list[str] = []
    for e in episodes:
        if e["kind"] == "discharged" and e["time_s"] >= start_s and e["patient"] not in earlier:
            earlier.append(e["patient"])
    patient_id = episodes[-1]["patient"] if episodes and episodes[-1]["kind"] == "admitted" else None
    named = live.get("patient") or {}
    name = named.get("name") if named.get("patient_id") == patient_id else None
    now = "no patient admitted" if patient_id is None else f"{name} ({patient_id})" if name else patient_id
    before = [p for p in earlier if p != patient_id]
    return f"{now}; discharged in the period: {', '.join(before)}" if before else now


def wall_time(time_s: float, zone: ZoneInfo) -> str:
    """An ISO 8601 time in ``zone`` (its offset written) for wall-clock times; none for a simulated bed's seconds."""
    return local_time(time_s, zone).isoformat(timespec="seconds") if time_s > WALL_CLOCK_AFTER_S else ""


def report_csv(report: ShiftReport) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, CSV_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for e in report.events:
        writer.writerow({**e, "time_utc": wall_time(e["time_s"], UTC_ZONE),
                         "time_local": wall_time(e["time_s"], report.zone), "time_s": repr(e["time_s"]),
                         "alarm": alarm_words(e.get("key")) if e.get("type") == "alarm" else ""})
    return out.getvalue()


def latin1(text: str) -> str:
    return text.encode("latin-1", "replace").decode("latin-1")


def report_pdf(report: ShiftReport) -> bytes:
    s = report.summary
    pdf = FPDF(format="A4")
    pdf.set_title(latin1(f"Shift report, bed {report.bed_id}"))
    pdf.add_page()
    pdf.set_font("Helvetica", "B", 16)
    line(pdf, f"Shift report, bed {report.bed_id}", 9)
    pdf.set_font("Helvetica", size=10)
    line(pdf, f"Patient: {report.patient}")
    line(pdf, f"Period {report.clock(s.start_s)} to {report.clock(s.end_s)} ({duration(s.end_s - s.start_s)})")
    stays = [e for e in report.events if e.get("type") == "episode"]
    if stays:
        heading(pdf, "Admissions and discharges")
        table(pdf, ("Time", "Event", "By"),
              [(report.clock(e["time_s"]), e.get("message") or e["kind"], e.get("user") or "") for e in stays],
              (40, 110, 40))
    heading(pdf, "Turns")
    line(pdf, f"{s.turns} turn(s); longest time without a turn {duration(s.longest_without_turn_s)}; "
              f"{s.turn_reminders} turn reminder(s)")
    turns = [e for e in report.history.turns if e["kind"] in ("repositioned", "recorded")]
    table(pdf, ("Time", "Turn", "By"),
          [(report.clock(e["time_s"]), e.get("message") or e["kind"], e.get("user") or "") for e in turns],
          (40, 110, 40))
    heading(pdf, f"Time at risk (at or above {s.threshold_mmhg:.0f} mmHg)")
    table(pdf, ("Region", "Peak mmHg", "Max dose", "Minutes at risk"),
          [(r.label, f"{r.peak_mmhg:.0f}", "-" if r.max_dose is None else f"{r.max_dose:.2f}",
            f"{r.minutes_above:.0f}") for r in s.regions], (80, 35, 35, 40))
    for title, alarms in (("Clinical alarms", s.clinical), ("Technical alarms", s.technical)):
        heading(pdf, title)
        table(pdf, ("Raised", "Priority", "Alarm", "Acknowledged by", "After", "Ended"),
              [(report.clock(a.raised_s), a.highest_priority, a.message or alarm_words(a.key),
                a.acknowledged_by or "not acknowledged", duration(a.acknowledge_delay_s),
                "-" if a.ended_s is None else report.clock(a.ended_s)) for a in alarms], (38, 18, 64, 30, 20, 20))
    heading(pdf, "Peak pressure by site (mmHg)")
    pressure_chart(pdf, report)
    return bytes(pdf.output())


def line(pdf: FPDF, text: str, height: float = 6) -> None:
    pdf.cell(0, height, latin1(text), new_x=XPos.LMARGIN, new_y=YPos.NEXT)


def heading(pdf: FPDF, text: str) -> None:
    pdf.ln(3)
    pdf.set_font("Helvetica", "B", 12)
    line(pdf, text, 8)
    pdf.set_font("Helvetica", size=9)


def table(pdf: FPDF, header: tuple[str, ...], rows: list[tuple[str, ...]], widths: tuple[int, ...]) -> None:
    if not rows:
        line(pdf, "None in this period.")
        return
    with pdf.table(col_widths=widths, width=sum(widths), align="LEFT", line_height=5) as t:
        for cells in (header, *rows):
            row = t.row()
            for cell in cells:
                row.cell(latin1(cell))


def pressure_chart(pdf: FPDF, report: ShiftReport) -> None:
    """The highest peak per site at each kept map, a line per site, with the threshold dashed."""
    history, threshold = report.history, report.summary.threshold_mmhg
    series: dict[str, list[tuple[float, float]]] = {}
    for row in history.regions:
        if row["zone"]:
            points = series.setdefault(row["zone"], [])
            if points and points[-1][0] == row["time_s"]:
                points[-1] = (row["time_s"], max(points[-1][1], row["peak_mmhg"]))
            else:
                points.append((row["time_s"], row["peak_mmhg"]))
    if not series:
        line(pdf, "No site was loaded in this period.")
        return
    if pdf.get_y() + CHART_H_MM + 30 > pdf.h - pdf.b_margin:
        pdf.add_page()
    x0, y0 = pdf.l_margin + 10, pdf.get_y() + 2
    span = max(history.end_s - history.start_s, 1.0)
    top = 20.0 * -(-max(threshold * 1.25, *(p for pts in series.values() for _, p in pts)) // 20.0)

    def at(t: float, p: float) -> tuple[float, float]:
        return x0 + (t - history.start_s) / span * CHART_W_MM, y0 + CHART_H_MM - p / top * CHART_H_MM

    pdf.set_draw_color(0, 0, 0)
    pdf.set_line_width(0.2)
    pdf.rect(x0, y0, CHART_W_MM, CHART_H_MM)
    pdf.set_font("Helvetica", size=7)
    for value in (0.0, top / 2, top):
        pdf.text(pdf.l_margin, at(history.start_s, value)[1] + 1, f"{value:.0f}")
    pdf.text(x0, y0 + CHART_H_MM + 4, latin1(report.clock(history.start_s)))
    pdf.text(x0 + CHART_W_MM - 32, y0 + CHART_H_MM + 4, latin1(report.clock(history.end_s)))
    with pdf.local_context(dash_pattern={"dash": 1, "gap": 1}):
        pdf.line(*at(history.start_s, threshold), *at(history.end_s, threshold))
    pdf.set_line_width(0.5)
    legend_y = y0 + CHART_H_MM + 9
    for n, (site, points) in enumerate(sorted(series.items())):
        colour = SITE_COLOURS[n % len(SITE_COLOURS)]
        pdf.set_draw_color(*colour)
        if len(points) > 1:
            pdf.polyline([at(t, p) for t, p in points])
        else:
            pdf.circle(*at(*points[0]), 1.0)
        pdf.set_text_color(*colour)
        pdf.text(x0 + (n % 4) * 45, legend_y + (n // 4) * 4, latin1(site_words(site)))
    pdf.set_text_color(0, 0, 0)
    pdf.set_draw_color(0, 0, 0)
    pdf.set_y(legend_y + 4 * (len(series) // 4 + 1))


bp = Blueprint("report", __name__)


@bp.route("/history/report.<kind>")
def download(kind: str):
    """The shift report as a PDF or the period's events as a CSV, downloaded as ``shift-<bed>.<kind>``."""
    if kind not in ("pdf", "csv"):
        abort(404, description=f"a shift report is report.pdf or report.csv, not report.{kind}")
    hours = requested_hours()
    live = snapshot()
    with reader() as s:
        made = shift_report(s, hours, live, threshold_mmhg(live), zone())
    if made is None:
        abort(404, description=NO_HISTORY)
    body = report_pdf(made) if kind == "pdf" else report_csv(made).encode()
    return Response(body, mimetype="application/pdf" if kind == "pdf" else "text/csv",
                    headers={"Content-Disposition": f'attachment; filename="shift-{made.bed_id}.{kind}"'})
