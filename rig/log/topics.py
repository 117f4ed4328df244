"""The trial log's channel names and MCAP profile, in a module that imports nothing, so that reading a log's
summary (``rig info``: :func:`rig.log.reader.trial_info`) does not load numpy; :mod:`rig.log.schemas` (the
channels' layouts and codecs) re-exports them."""

RAW_TOPIC = "/raw"
LOG25_TOPIC = "/log25"
EVENTS_TOPIC = "/events"
STATS_TOPIC = "/loop_stats"
MCAP_PROFILE = "rig-trial"
