"""Telemetry *out* of the service (MQTT), and what may come *in* on MQTT (leader position, commands)."""
