"""The transport core: keys, messages, config, sessions and services (imports nothing above it)."""
