"""Fault-injection suite: the compensation service under real faults, real processes."""
