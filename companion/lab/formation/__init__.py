"""Formations in lockstep: one leader, N followers, one service core per follower, scored per follower."""
