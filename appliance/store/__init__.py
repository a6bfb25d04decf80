"""Persistence of the event log, alert checkpoints and pressure history in one SQLite file."""

from appliance.store.database import SchemaTooNew, Store, StoreClosed, StoreCorrupt, StoreError

__all__ = ["SchemaTooNew", "Store", "StoreClosed", "StoreCorrupt", "StoreError"]
