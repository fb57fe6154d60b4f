"""The digital twin: scenario files, cell sites, receiver routes and a 3GPP statistical channel.

Typical use::

    from deepsync.twin import build_twin, load_scenario
    twin = build_twin(load_scenario("config/scenarios/campus.yaml"))
    paths = twin.channel.paths(0, t=0.0)
"""

from deepsync.twin.scenario import Scenario, load_scenario
from deepsync.twin.world import Twin, build_twin

__all__ = ["Scenario", "Twin", "build_twin", "load_scenario"]
