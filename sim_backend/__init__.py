"""Simulated plant, virtual devices (the other end of every wire), scenarios and backends."""
