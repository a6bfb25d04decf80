"""Failed-login limits that slow password guessing without letting a guesser lock staff out.

Three counts, each over a sliding window and kept in memory (a restart forgets
them, which only helps a guesser as much as a restart costs him):

* per account and address: a few failures lock that account from that address;
* per address: a higher count locks the address for every account, so one
  machine cannot guess through the account list;
* per account from every address: a still higher count locks the account, to
  slow guessing spread over many addresses, but never for the bedside's own
  screen (a loopback address), so the staff at the bed can always log in
  however many guesses come from the network.

A success clears only its own account-and-address count: logging in to one's own
account must not wipe the record of one's guesses at others.
"""

from __future__ import annotations

import ipaddress
import threading
import time
from collections import deque

PAIR_ATTEMPTS, ADDRESS_ATTEMPTS, ACCOUNT_ATTEMPTS = 5, 20, 50
WINDOW_S = 300.0
SWEEP_EVERY = 1000          # failures between sweeps of forgotten keys, so memory stays bounded


def is_loopback(address: str | None) -> bool:
    """Whether ``address`` is this machine's own (127.0.0.0/8 or ::1)."""
    try:
        return ipaddress.ip_address(address or "").is_loopback
    except ValueError:
        return False


class LoginLimiter:
    """The three failure counts of the module's docstring; ``name`` None counts the address alone."""

    def __init__(self, pair_attempts: int = PAIR_ATTEMPTS, address_attempts: int = ADDRESS_ATTEMPTS,
                 account_attempts: int = ACCOUNT_ATTEMPTS, window_s: float = WINDOW_S):
        self.limits = {"pair": pair_attempts, "addr": address_attempts, "account": account_attempts}
        self.window_s = window_s
        self._failures: dict[tuple, deque] = {}
        self._since_sweep = 0
        self._lock = threading.Lock()

    def _keys(self, name: str | None, address: str | None, *, checking: bool) -> list[tuple]:
        keys: list[tuple] = [("addr", address)]
        if name is not None:
            keys.append(("pair", name, address))
            if not (checking and is_loopback(address)):
                keys.append(("account", name))
        return keys

    def blocked_for_s(self, name: str | None, address: str | None, now: float | None = None) -> float:
        """Seconds until ``name`` may be tried again from ``address`` (0: now)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            wait = 0.0
            for key in self._keys(name, address, checking=True):
                failures = self._recent(key, now)
                if len(failures) >= self.limits[key[0]]:
                    wait = max(wait, failures[-self.limits[key[0]]] + self.window_s - now)
            return wait

    def failed(self, name: str | None, address: str | None, now: float | None = None) -> bool:
        """Count a failure; True if it is the one that locks (so the lock is logged once, not every refusal)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            locks = False
            for key in self._keys(name, address, checking=False):
                failures = self._recent(key, now)
                failures.append(now)
                locks = locks or len(failures) == self.limits[key[0]]
                self._failures[key] = failures
            self._since_sweep += 1
            if self._since_sweep >= SWEEP_EVERY:
                self._sweep(now)
            return locks

    def succeeded(self, name: str, address: str | None) -> None:
        with self._lock:
            self._failures.pop(("pair", name, address), None)

    def _recent(self, key: tuple, now: float) -> deque:
        failures = self._failures.get(key, deque())
        while failures and failures[0] <= now - self.window_s:
            failures.popleft()
        return failures

    def _sweep(self, now: float) -> None:
        self._since_sweep = 0
        for key in [key for key, failures in self._failures.items() if not self._recent(key, now)]:
            del self._failures[key]
