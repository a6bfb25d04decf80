"""The screen's user accounts, password rules and audit log, and the owner-only files that keep them.

Below both the web screen and provisioning, which makes the first administrator, so neither imports the other.
"""
