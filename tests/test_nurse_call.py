"""The nurse-call relays on emulated GPIO lines: closed while an alarm of their priority waits for a nurse, open
once it is acknowledged; latched or following the condition; a line that cannot be set is a technical alarm
and monitoring goes on."""

import errno
from types import SimpleNamespace

import pytest
from test_ward import ward_daemon

from appliance.alerts.alarms import AWAITING_ACK, AlarmCondition, AlarmEngine
from appliance.alerts.nurse_call import NurseCallRelays
from appliance.drivers.bus import LineRequest
from appliance.drivers.emulated.buses import BusTiming, EmulatedGPIOLines, GPIOBank
from appliance.drivers.emulated.clock import SimulatedClock
from appliance.errors import ConfigError
from appliance.service.config import config_from_mapping

LINES = {"high": "GPIO19", "medium": "GPIO20", "low": "GPIO21"}


def relays(mode="latched", active_low=False):
    bank = GPIOBank(SimulatedClock(), [*LINES.values(), "GPIO12"], [])
    level = 1 if active_low else 0
    lines = EmulatedGPIOLines(bank, LineRequest(outputs=dict.fromkeys(LINES.values(), level), inputs={}),
                              "nurse call", BusTiming())
    return bank, lines, NurseCallRelays(lines, LINES, mode=mode, active_low=active_low)


def closed(lines, active_low=False):
    """The priorities whose relay is closed, as the lines stand."""
    level = 0 if active_low else 1
    return {p for p, line in LINES.items() if lines.get_values([line])[line] == level}


def condition(key, priority, latching=True):
    return AlarmCondition(key, "clinical", priority, latching, f"{key} alarm")


@pytest.mark.parametrize("active_low", [False, True])
def test_latched_relays_close_per_priority_until_acknowledged_even_after_the_condition_clears(active_low):
    _, lines, nurse_call = relays(active_low=active_low)
    engine = AlarmEngine()
    assert closed(lines, active_low) == set()                  # open from the request on
    high, medium = condition("pressure:sacrum", "high"), condition("turn:due", "medium")
    engine.assess(1.0, {"pressure:sacrum": (high, None), "turn:due": (medium, None)})
    nurse_call.show(engine.alarms())
    assert closed(lines, active_low) == {"high", "medium"}
    engine.assess(2.0, {"turn:due": (medium, None)})           # the sacrum's condition cleared: latched
    assert [a.state for a in engine.alarms() if a.priority == "high"] == [AWAITING_ACK]
    engine.pause_audio(2.5, "nurse.smith", 60.0)               # quiet, but still waiting for a nurse
    nurse_call.show(engine.alarms())
    assert closed(lines, active_low) == {"high", "medium"}
    engine.acknowledge(3.0, engine.alarms()[0].alarm_id, "nurse.smith")
    nurse_call.show(engine.alarms())
    assert closed(lines, active_low) == {"medium"}
    nurse_call.close()
    assert closed(lines, active_low) == set()


def test_following_relays_open_when_the_condition_clears_and_on_acknowledge():
    _, lines, nurse_call = relays(mode="follow")
    engine = AlarmEngine()
    high, low = condition("pressure:sacrum", "high"), condition("posture:unknown", "low")
    engine.assess(1.0, {"pressure:sacrum": (high, None), "posture:unknown": (low, None)})
    nurse_call.show(engine.alarms())
    assert closed(lines) == {"high", "low"}
    engine.assess(2.0, {"posture:unknown": (low, None)})       # cleared but unacknowledged: no longer calling
    nurse_call.show(engine.alarms())
    assert closed(lines) == {"low"}
    engine.acknowledge(3.0, next(a.alarm_id for a in engine.alarms() if a.priority == "low"), "nurse.smith")
    nurse_call.show(engine.alarms())
    assert closed(lines) == set()


def test_a_line_that_cannot_be_set_is_a_fault_until_it_can():
    bank, lines, nurse_call = relays()
    engine = AlarmEngine()
    engine.assess(1.0, {"pressure:sacrum": (condition("pressure:sacrum", "high"), None)})
    bank.break_line("GPIO19")
    nurse_call.show(engine.alarms())
    assert "GPIO19" in nurse_call.fault and "Input/output error" in nurse_call.fault
    assert list(nurse_call.conditions()) == ["technical:nurse-call"]
    bank.mend_line("GPIO19")
    nurse_call.show(engine.alarms())
    assert nurse_call.fault is None and nurse_call.conditions() == {} and closed(lines) == {"high"}


def calling(daemon):
    """The priorities with an unacknowledged alarm open: the relays a latched nurse call closes."""
    return {a.priority for a in daemon.pipeline.engine.alarms() if not a.acknowledged}


def test_the_monitor_closes_the_relay_on_a_high_alarm_opens_it_on_acknowledge_and_monitors_through_a_fault(
        small_mat_calibration, tmp_path):
    bank, lines, nurse_call = relays()
    daemon = ward_daemon(small_mat_calibration, tmp_path, [])
    daemon.nurse_call = nurse_call
    try:
        for _ in range(100):                                   # the sacrum's alarm, escalated to high
            daemon.step()
            if any(a.priority == "high" for a in daemon.pipeline.engine.alarms()):
                break
        alarm = next(a for a in daemon.pipeline.engine.alarms() if a.priority == "high")
        assert alarm.key.startswith("pressure:") and "high" in closed(lines) and closed(lines) == calling(daemon)
        for each in daemon.pipeline.engine.alarms():
            daemon.acknowledge(each.alarm_id, "nurse.smith")
        daemon.step()
        assert calling(daemon) == set() and closed(lines) == set()

        bank.break_line(LINES["medium"], errno.EIO)
        maps = daemon.maps
        daemon.step()                                          # the write fails at this frame's end
        daemon.step()                                          # and is this frame's technical alarm
        technical = [a for a in daemon.pipeline.engine.alarms() if a.key == "technical:nurse-call"]
        assert len(technical) == 1 and "cannot be set (OSError: [Errno 5]" in technical[0].message
        assert daemon.maps == maps + 2                         # monitoring went on
        assert "medium" in calling(daemon) and closed(lines) == set()   # the broken lines kept their last level
        bank.mend_line(LINES["medium"])
        daemon.step()                                          # written again: the medium relay closes
        assert "medium" in closed(lines) and closed(lines) == calling(daemon)
        daemon.step()                                          # and the fault's alarm is over
        assert not [a for a in daemon.pipeline.engine.alarms() if a.key == "technical:nurse-call"]
        assert closed(lines) == calling(daemon)
    finally:
        daemon.close()
    assert closed(lines) == set()


@pytest.mark.parametrize(("table", "message"), [
    ({}, "need a line for at least one priority"),
    ({"urgent": "relay"}, "unknown key 'urgent'|'urgent'"),
    ({"high": "relay", "low": "relay"}, "needs a line of its own"),
    ({"high": "relay", "mode": "sticky"}, "mode must be one of latched, follow, got 'sticky'"),
    ({"high": "relay", "active_low": "yes"}, "active_low must be true or false"),
])
def test_a_bad_nurse_call_section_is_refused_naming_the_key(table, message):
    with pytest.raises(ConfigError, match=message):
        config_from_mapping({"monitor": {"source": "emulated"}, "notify": {"nurse_call": table}})


def test_the_nurse_call_section_is_off_by_default_and_needs_a_board():
    assert config_from_mapping({}).nurse_call is None
    with pytest.raises(ConfigError, match="needs a board: the virtual bed has no relay lines"):
        config_from_mapping({"notify": {"nurse_call": {"high": "nurse_call_high"}}})
    config = config_from_mapping({"monitor": {"source": "emulated"},
                                  "notify": {"nurse_call": {"high": "nurse_call_high", "mode": "follow"}}})
    assert (config.nurse_call.relays, config.nurse_call.mode, config.nurse_call.active_low) == \
        ({"high": "nurse_call_high"}, "follow", False)


class Board:
    """The board's side of the lines: the emulated header, handing out lines as ``LinuxBoard.gpio`` does."""

    def __init__(self, roles):
        self.roles = roles
        self.bank = GPIOBank(SimulatedClock(), list(roles.values()), [])

    def gpio(self, request, *, consumer):
        return EmulatedGPIOLines(self.bank, request, consumer, BusTiming())

    @property
    def front_end(self):
        return SimpleNamespace(profile=SimpleNamespace(gpio=self.roles))


def test_the_relays_are_found_by_their_roles_in_the_board_profile_and_start_open():
    from appliance.service.assemble import _nurse_call

    roles = {"buzzer": "GPIO12", "status_led": "GPIO16", "nurse_call_high": "GPIO19", "nurse_call_low": "GPIO21"}
    board = Board(roles)
    source = SimpleNamespace(board=board, front_end=board.front_end)
    config = config_from_mapping({"monitor": {"source": "emulated"}, "notify": {
        "gpio": {}, "nurse_call": {"high": "nurse_call_high", "low": "nurse_call_low", "active_low": True}}})
    nurse_call = _nurse_call(config, source)
    assert nurse_call.relays == {"high": "GPIO19", "low": "GPIO21"}
    assert (board.bank.level("GPIO19"), board.bank.level("GPIO21")) == (1, 1)        # open, active low
    engine = AlarmEngine()
    engine.assess(1.0, {"pressure:sacrum": (condition("pressure:sacrum", "high"), None)})
    nurse_call.show(engine.alarms())
    assert (board.bank.level("GPIO19"), board.bank.level("GPIO21")) == (0, 1)
    for table, message in (({"high": "nurse_call_medium"}, "no gpio role 'nurse_call_medium'"),
                           ({"high": "buzzer"}, "line GPIO12 is the buzzer's or the LED's")):
        config = config_from_mapping({"monitor": {"source": "emulated"},
                                      "notify": {"gpio": {}, "nurse_call": table}})
        with pytest.raises(ConfigError, match=message):
            _nurse_call(config, SimpleNamespace(board=Board(roles), front_end=board.front_end))
