"""The HL/LL interface (Sec. 2.2-2.3): how a high-level action becomes body actions.

A controller turns one high-level action into low-level actions for as long as that
action lasts (a fragment's length, a gait cycle, or one step for end_to_end);
`ControlledEnv` asks for a new high-level action only when the current one has ended,
while the high-level core still sees every step.
"""
