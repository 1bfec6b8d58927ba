"""Formations in lockstep: one leader, N followers, one flight per follower, scored per follower."""
