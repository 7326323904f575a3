"""Bags: reading and writing them, replaying the decisions in one, showing one, repairing one."""
