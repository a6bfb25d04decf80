"""Clock times on the screen, in the site's time zone (``appliance.service.settings.shown_time_zone``).

The zone is looked up once a request (the settings file, else the monitor's
live view), so every time on a page, a chart and a report is read in the same
zone, and a zone changed by the admin shows on the next page.
"""

from __future__ import annotations

from zoneinfo import ZoneInfo

from flask import current_app, g

from appliance.service.live import read_live
from appliance.service.settings import shown_time_zone
from appliance.time_zones import clock_text, time_zone


def zone_name() -> str:
    """The IANA name of the zone this request shows clock times in."""
    if "time_zone" not in g:
        try:
            live = read_live(current_app.config["LIVE_PATH"])
        except ValueError:                  # damaged: the live view says so; the settings file may name the zone
            live = None
        g.time_zone = shown_time_zone(current_app.config["STORE_PATH"].parent, live)
    return g.time_zone


def zone() -> ZoneInfo:
    return time_zone(zone_name())


def clock(time_s: float) -> str:
    """A monitor time as a person reads it: wall-clock times as dates and times in the site's zone, simulated ones
    as h:mm:ss."""
    return clock_text(time_s, zone())
