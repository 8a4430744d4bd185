"""Recording what the chair saw and decided (MCAP), replaying it, and the live view.

- :mod:`omnid.record.settings` — the ``record`` configuration section;
- :mod:`omnid.record.topics` — topic names, Foxglove schemas, encoders;
- :mod:`omnid.record.recorder` — the bounded queue and the writer thread, segments, budget;
- :mod:`omnid.record.tap` — ``RecordingCore``, the core's contract with recording;
- :mod:`omnid.record.reader` — reading a recording back (one-line errors);
- :mod:`omnid.record.replay` — this version's perception and safety layer on a recording;
- :mod:`omnid.record.plots` — the top-down picture and the timeline (PNG, drawn with OpenCV).

Needs the ``record`` extra (``pip install 'omnid[record]'``: ``mcap``, ``foxglove-sdk``,
``mcap-protobuf-support``); everything else in omnid works without it. docs/recording.md
lists the topics.
"""
