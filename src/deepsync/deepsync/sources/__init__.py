"""Where envelope chunks come from: every recording a user may have, as one kind of stream.

A :class:`Source` yields :class:`~deepsync.types.EnvelopeChunk` s, one per LTE frame, and says
which receiver chain made them (``frontend``: the sync templates are built from it, and its
``adc_rate_hz`` is the stream's sample rate). Sources:

* :class:`RawFileSource`: raw headerless files (RTL-SDR ``cu8``, HackRF ``ci8``, ``ci16_le``,
  ``cf32_le`` I/Q; ``ri16_le``, ``rf32_le`` envelopes), format and rate given by the user;
* :class:`SigmfSource`: SigMF recordings, format, rate, centre frequency and time from metadata;
* :class:`BagSource`: rosbag2 bags of the envelope topic, front end from their provenance;
* :class:`SimulatorSource`: the live simulator, a scenario's stream computed as it is read;
* :class:`LiveSource`: a live receiver's byte stream (``tcp://HOST:PORT``, ``rtl_tcp://HOST:PORT``,
  ``-`` for standard input, a serial device, ``soapy://DRIVER``), read in a background thread,
  stamped on the receiver's clock, its stalls, closes and drops said as health events
  (:mod:`deepsync.sources.live`; docs/live_receivers.md);
* :func:`open_source`: the right one for a path or a live address (:func:`open_live`).

Complex I/Q becomes an envelope as a square-law detector would make it, ``|x - zero|^2``, under
one reproducible rule stated in :mod:`deepsync.sources.envelope`.
"""

from .bagfile import BagSource, bag_frontend
from .base import Source
from .envelope import envelope_codes, squared_iq_frontend
from .formats import SampleFormat
from .live import LiveOptions, LiveSource
from .opener import open_live, open_source
from .rawfile import RawFileSource, read_iq
from .sigmf_recording import SigmfSource
from .simulated import SimulatorSource

__all__ = [
    "BagSource",
    "LiveOptions",
    "LiveSource",
    "RawFileSource",
    "SampleFormat",
    "SigmfSource",
    "SimulatorSource",
    "Source",
    "bag_frontend",
    "envelope_codes",
    "open_live",
    "open_source",
    "read_iq",
    "squared_iq_frontend",
]
