"""The motion plan: one pure pipeline from a prescription to the checked plan the real-time worker plays.

    prescription.py  the prescription, validated once at the edge (one pydantic model: cue kinds, washout,
                     shaping, limits, cueing algorithm, seed)
    limits.py        the limits a segment runs under (the robot's, only ever tightened) and their codes
    ramps.py         bounded-jerk transitions: soft start / fade out gains, stops, return to neutral
    timeline.py      each segment as played: cue × gains → cueing algorithm → stance poses → return ramp
    check.py         the independent batch check of every sample against every limit
    build.py         `build_plan`: validated prescription + twin (+ patient, rate, config) → checked plan

The worker (`server.realtime`), the preview, `ssp-rehab realtime check` and `ssp-rehab cueing plan` all call
`build_plan`; nothing here does I/O.
"""
