"""The core layer: the spec, the state and its pure in-graph functions, tags and the
registries. Imports nothing above it (host, writers, integrations)."""
