"""Saving: which save times a step covers."""



# ---------------------------------------------------------------------------- saving
def saved_in_step(save_ts, t, t_end):
    """Which save times a step from t writes: those in (t, t_end], t_end the event time in a
    step with an event, the step's end otherwise (a time equal to an event time is saved
    before the jump: the pre-event state)."""
    return (save_ts > t) & (save_ts <= t_end)
