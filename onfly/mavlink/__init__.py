"""The MAVLink bridge: link, NED/FRD frame conversion, vehicle state, setpoint streaming,
PX4 offboard and ArduPilot guided sequencing, companion-side failsafes, and a simulated
MAVLink vehicle for tests and bench runs.

NED and FRD exist only in :mod:`onfly.mavlink.frames`; everything this package hands out is
ENU/FLU (:mod:`planning.frames`).
"""
