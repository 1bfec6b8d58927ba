"""What the follower sees, for people: a live view over Foxglove's WebSocket protocol and MCAP flight logs.

:class:`~companion.viz.recorder.FlightRecorder` observes the flight (every processed frame, control step
and transition) and hands what it saw to a worker thread, which builds the messages and writes them to its
sinks (:mod:`companion.viz.sinks`): the live server, an MCAP file, or both. The flight loop only puts
references into bounded mailboxes; images are encoded on the worker at a bounded rate. Channels, schemas and
frame ids are in :mod:`companion.viz.channels` (docs/visualisation.md shows them in Foxglove or Lichtblick).
"""
