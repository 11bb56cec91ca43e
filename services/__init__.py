"""Processes of the twin: thin shells that subscribe, call twin_core, and publish."""
