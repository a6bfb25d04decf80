"""Bedside EIT pressure-sore monitor.

Data flows one way: ``drivers`` (buses, chips, scan engine) -> ``core``
(layouts, forward models, reconstruction) -> ``alerts`` -> ``store`` and
publishing -> the web UI. ``import appliance`` needs only numpy and scipy.
"""

__version__ = "0.1.0"
