"""The ward link over the ward's MQTT broker: topics, QoS and the broker's acknowledgement.

Topics (``<prefix>`` is ``topic_prefix``, "appliance" by default)::

    <prefix>/<bed_id>/alarm    QoS 1: one alarm Event as JSON, with "bed_id" and "seq"
                               {time_s, type: "alarm", kind, priority, category, key,
                                site, posture, x_mm, y_mm, alarm_id, message, user,
                                channel, patient, bed_id, seq}
    <prefix>/<bed_id>/turn     QoS 1: one turn Event (type "turn"), the same fields
    <prefix>/<bed_id>/episode  QoS 1: admitted or discharged, the same fields
    <prefix>/<bed_id>/confirm  QoS 1, from the ward station: {seq, station, confirmed_at}
    <prefix>/<bed_id>/command  QoS 1, from the ward station: acknowledge an alarm, record
                               a turn (``appliance.alerts.ward_commands``)
    <prefix>/<bed_id>/command-result   QoS 1: the bed's answer to each command
    <prefix>/<bed_id>/status   QoS 1, retained: "online" once connected; "offline" on
                               close, and as the last will when the connection dies.
    <prefix>/<bed_id>/summary  QoS 0, retained: the bed at a glance about once a second
                               (``appliance.service.daemon.ward_summary``) with
                               "written_at" (unix time) and "seq", the highest number
                               handed out when it was made: its alarms already hold
                               every event up to that number.

The broker's PUBACK says only that the broker has an event (Mosquitto: in memory);
the link (``appliance.alerts.wardlink``) waits for the station's confirmation.
"""

from __future__ import annotations

import json
import logging
import threading

import paho.mqtt.client as mqtt

from appliance.alerts.events import EVENT_TYPES
from appliance.alerts.ward_commands import COMMAND_TOPIC, RESULT_TOPIC
from appliance.alerts.wardlink import WardLink
from appliance.store.outbox import Outbox

log = logging.getLogger(__name__)


class MqttTransport:
    """``bed_id``'s topics on the broker at ``host``:``port``, as client ``client_id``."""

    peer = "the ward broker"

    def __init__(self, host: str, port: int, bed_id: str, *, client_id: str, topic_prefix: str = "appliance",
                 keepalive_s: int = 30, username: str | None = None, password: str | None = None, ca_file=None):
        self.host, self.port, self.keepalive_s = host, port, keepalive_s
        base = f"{topic_prefix}/{bed_id}"
        self.topics = {kind: f"{base}/{kind}" for kind in EVENT_TYPES}
        self.status_topic, self.summary_topic, self.confirm_topic = f"{base}/status", f"{base}/summary", \
            f"{base}/confirm"
        self.command_topic, self.result_topic = f"{base}/{COMMAND_TOPIC}", f"{base}/{RESULT_TOPIC}"
        self._link: WardLink | None = None
        self._command_subscription: int | None = None           # the mid of its subscription
        self._in_flight: dict[int, int] = {}                     # mid -> seq, awaiting PUBACK
        self._lock = threading.Lock()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self.client.will_set(self.status_topic, "offline", qos=1, retain=True)
        if username is not None:
            self.client.username_pw_set(username, password)
        if ca_file is not None:
            self.client.tls_set(ca_certs=str(ca_file))          # the broker's name is checked against its cert
        self.client.reconnect_delay_set(min_delay=1, max_delay=10)
        self.client.on_connect = self._on_connect
        self.client.on_subscribe = self._on_subscribe
        self.client.on_disconnect = self._on_disconnect
        self.client.on_publish = self._on_publish
        self.client.on_message = self._on_message
        self.client.message_callback_add(self.confirm_topic, self._on_confirm)
        self.client.message_callback_add(self.command_topic, self._on_command)

    def start(self, link: WardLink) -> None:
        self._link = link
        self.client.connect_async(self.host, self.port, keepalive=self.keepalive_s)
        self.client.loop_start()

    def send_event(self, seq: int, event: dict) -> bool:
        payload = json.dumps({**event, "bed_id": self._bed().bed_id, "seq": seq})
        # Not under our lock: paho's thread calls _on_publish holding its own lock, and publish() takes that lock,
        # so holding ours across it deadlocks against a PUBACK. A PUBACK that comes before the mid is noted is
        # missed, and the event is sent again after resend_after_s like any other unacknowledged one.
        info = self.client.publish(self.topics[event["type"]], payload, qos=1)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            return False
        with self._lock:
            self._in_flight[info.mid] = seq
        return True

    def send_summary(self, payload: str) -> bool:
        return self.client.publish(self.summary_topic, payload, qos=0, retain=True).rc == mqtt.MQTT_ERR_SUCCESS

    def send_answer(self, payload: str) -> bool:
        info = self.client.publish(self.result_topic, payload, qos=1)
        if info.rc != mqtt.MQTT_ERR_SUCCESS:
            log.warning("ward link: %s", mqtt.error_string(info.rc))
        return info.rc == mqtt.MQTT_ERR_SUCCESS

    def connected(self) -> bool:
        return self.client.is_connected()

    def close(self, timeout_s: float) -> None:
        if self.client.is_connected():
            info = self.client.publish(self.status_topic, "offline", qos=1, retain=True)
            try:
                info.wait_for_publish(timeout_s)
            except (RuntimeError, ValueError) as exc:
                log.warning("ward link: could not publish the offline status: %s", exc)
        release(self.client)

    def _bed(self) -> WardLink:
        if self._link is None:
            raise RuntimeError("the MQTT transport has not been started by a ward link")
        return self._link

    # paho's network thread.

    def _on_connect(self, client, userdata, flags, reason_code, properties) -> None:
        if reason_code.is_failure:
            log.warning("ward link: the broker refused the connection: %s", reason_code)
            return
        client.publish(self.status_topic, "online", qos=1, retain=True)
        client.subscribe(self.confirm_topic, qos=1)
        # Apart: a broker whose ACL predates the ward's commands refuses this one, and must still get the alarms.
        self._command_subscription = client.subscribe(self.command_topic, qos=1)[1]

    def _on_subscribe(self, client, userdata, mid, reason_codes, properties) -> None:
        if mid == self._command_subscription:
            if any(code.is_failure for code in reason_codes):
                log.error("ward link: the broker refused %s (%s): the ward station's commands cannot reach this "
                          "bed; write its ACL again with appliance ward-broker", self.command_topic, reason_codes)
            return
        if any(code.is_failure for code in reason_codes):
            log.error("ward link: the broker refused the confirmations' topic %s: %s", self.confirm_topic,
                      reason_codes)
            return
        with self._lock:
            self._in_flight.clear()
        self._bed().transport_ready()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties) -> None:
        with self._lock:
            self._in_flight.clear()
        self._bed().transport_down()

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        with self._lock:
            seq = self._in_flight.pop(mid, None)
        if seq is not None:
            self._bed().transport_held(seq)

    def _on_message(self, client, userdata, message) -> None:
        log.warning("ward link: unexpected message on %s ignored", message.topic)

    def _on_confirm(self, client, userdata, message) -> None:
        try:
            body = json.loads(message.payload)
            seq, station = body["seq"], body["station"]
        except (ValueError, TypeError, KeyError) as exc:
            log.warning("ward link: bad confirmation ignored: %s", exc)
            return
        self._bed().transport_confirmed(seq, station)

    def _on_command(self, client, userdata, message) -> None:
        self._bed().transport_command(message.payload)


def mqtt_ward_link(host: str, port: int, bed_id: str, outbox: Outbox, *, client_id: str,
                   topic_prefix: str = "appliance", keepalive_s: int = 30, username: str | None = None,
                   password: str | None = None, ca_file=None, **link_options) -> WardLink:
    """A ward link for ``bed_id`` over the broker at ``host``:``port``; ``link_options`` are
    :class:`~appliance.alerts.wardlink.WardLink`'s (``confirm``, ``confirm_timeout_s``, ...)."""
    transport = MqttTransport(host, port, bed_id, client_id=client_id, topic_prefix=topic_prefix,
                              keepalive_s=keepalive_s, username=username, password=password, ca_file=ca_file)
    return WardLink(transport, bed_id, outbox, **link_options)


def release(client: mqtt.Client) -> None:
    """Disconnect ``client``, stop its network thread and close its wake-up socket pair, which paho would close
    only when the client is collected: in a reference cycle that can come after the sockets' own finalisers,
    which then warn of unclosed sockets."""
    client.disconnect()
    client.loop_stop()
    client._reset_sockets(sockpair_only=True)     # private: paho has no public call for it
