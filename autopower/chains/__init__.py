"""The real robot software components of the search-and-rescue mission, and their data sources.

* "Blob": ``CameraSource`` renders 230415-byte PPM frames of moving coloured victims;
  ``BlobFinder`` (CMVision-style) reports blobs in <= 200 bytes.
* "Loc": ``LocSource`` simulates a robot driving through a building (odometry + two laser
  scans, ~1059 bytes); ``MonteCarloLocaliser`` estimates its pose (~805 bytes) and can be
  migrated mid-run through ``export_state``/``import_state``.

The runtime uses ``make_source``, ``make_component`` and ``score_output``; ``profile_components``
measures latencies and message sizes on the current machine. Components of your own (plug-ins
named in a scenario or by an entry point) are imported and registered by ``plugins``.

May import: `autopower.errors` only. A component knows nothing of placement, radios or Zenoh.
"""

from autopower.chains.base import (
    Component,
    ComponentStateError,
    MalformedInputError,
    ScoredSource,
    Source,
    StatefulComponent,
    UnknownComponentTypeError,
)
from autopower.chains.blobfinder import BlobFinder, decode_report
from autopower.chains.camera import CameraSource, SyntheticCamera
from autopower.chains.mcl import MonteCarloLocaliser, decode_estimate
from autopower.chains.plugins import ENTRY_POINT_GROUP, register_scenario_components
from autopower.chains.profile import profile_components
from autopower.chains.registry import (
    ComponentType,
    component_types,
    get_component_type,
    make_component,
    make_source,
    register_component_type,
    score_output,
    unregister_component_type,
)
from autopower.chains.world import LocSource

__all__ = [
    "ENTRY_POINT_GROUP",
    "BlobFinder",
    "CameraSource",
    "Component",
    "ComponentStateError",
    "ComponentType",
    "LocSource",
    "MalformedInputError",
    "MonteCarloLocaliser",
    "ScoredSource",
    "Source",
    "StatefulComponent",
    "SyntheticCamera",
    "UnknownComponentTypeError",
    "component_types",
    "decode_estimate",
    "decode_report",
    "get_component_type",
    "make_component",
    "make_source",
    "profile_components",
    "register_component_type",
    "register_scenario_components",
    "score_output",
    "unregister_component_type",
]
