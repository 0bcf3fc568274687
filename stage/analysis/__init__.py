"""Movement analysis: body features for pieces, gait and body reports from recordings.

``features``: joint angles, distances, height, lean, centre of mass (pure
functions of a skeleton) and ``FeatureTracker`` (speeds, acceleration,
quantity of motion, frame by frame). ``trajectory``: a body over time with
missing values. ``integrate``: seed 003's resampled average over a chosen
subset of a recording's sensors. ``gait``: foot events and gait parameters
(seed 003), offline and live (``LiveSteps``, for pieces). ``kpi``: seed
004's body KPIs. ``agreement``: seed 003's bias, RPC, CV and ICC(A,1).
``analyze`` and ``report``: what ``stage analyze`` runs and draws.

The layer sits above the sensors (it reads recordings and the simulator's
truth) and below pieces and views (which use its features); it never
touches the engine: live, it reads ``FusedFrame``/``Body`` as any view does.
"""
