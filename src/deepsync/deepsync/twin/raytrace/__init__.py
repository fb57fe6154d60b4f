"""Ray-traced channels on real city geometry with Sionna RT (the optional extra ``deepsync[raytrace]``).

Modules: ``backend`` (importing Sionna, its LLVM), ``buildings`` (footprints and roof heights),
``city`` (GeoJSON footprints extruded into a scene), ``scenes`` (scenes by name or file, tied to
the map frame), ``sites`` (rooftops, three-sector sites, route checks), ``tracing`` (paths from
an antenna to receiver points, cached), ``channel`` (``RayTracedChannel``), ``build`` (a
scenario's channel). Nothing here imports Sionna until a trace runs.

Tracing a site to a list of positions (the map frame, ENU m)::

    from deepsync.geo import LocalFrame
    from deepsync.twin.raytrace.scenes import open_scene
    from deepsync.twin.raytrace.tracing import TraceSettings, trace_paths
    frame = LocalFrame(48.1374, 11.5755, 520.0)
    scene = open_scene("munich", frame, cache_dir)
    traced = trace_paths(scene, site_enu, 2.66e9, positions_enu, TraceSettings(), cache_dir)
    traced.at(0)   # position 0's paths: delays_s, gains, los, interactions, directions
    static_paths(traced, 0, SectorAntenna(azimuth_deg=120.0, downtilt_deg=6.0))  # a sector's Paths there

(``static_paths`` from ``deepsync.twin.raytrace.channel``, ``SectorAntenna`` from ``deepsync.twin.antenna``.)
"""
