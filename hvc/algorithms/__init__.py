"""Learners: V-trace actor-critic, SVG(0) with Retrace, Wolpertinger query selection."""
