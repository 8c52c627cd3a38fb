"""The zenoh API of the afmctl service: settings, payload schemas, the bridge and its own process
(keys and payloads in docs/ZENOH.md)."""
