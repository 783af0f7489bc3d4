"""Names of the built-in method presets, in a module that imports nothing (the CLI's parsers read them without
loading the method registry, which pulls in depth sources, readers and their libraries)."""

#: The best preset that runs offline (measured on realmini-dev val, docs/benchmarks.md).
BEST_OFFLINE = "best-offline"
#: The best offline preset that needs depth at the reference only (queries without depth: a service anchor).
BEST_OFFLINE_REFERENCE_DEPTH = "best-offline-pnp"
