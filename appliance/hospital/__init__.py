"""The hospital's beds on a replicated message engine: a NATS cluster with JetStream, configured from one file."""
