"""The host layer: the `Logger`, the report's trip from the device to the host, and the
records writers receive. Builds on `_core`, never on writers or integrations."""
