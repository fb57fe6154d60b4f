"""Tower database: the cells plausible where the receiver is, grouped by site.

The envelope keeps timing far better than identity, so the cell search leans on this list:
it scores only these PCIs (known-PCI mode) and a site, not a sector, is the TDOA anchor.
A site's position and frame-timing offset may be unknown (null): then it still names cells
but cannot anchor a position fix. Fusion also needs the ``origin`` (the ``map`` frame's WGS84
origin, REP-105; ``height_m`` is the ground's ellipsoidal height, under every antenna ``height_m``)
and, for drifting site clocks, the instant the offsets hold (``timing_epoch_utc``).

A site's frame timing is ``timing_offset_us`` (frame 0 start modulo 10 ms, against network time
at ``timing_epoch_utc``) plus ``timing_drift_ns_per_s`` for every second since then (its
oscillator: a site 20 ppb fast drifts by -20 ns/s). The ``*_std_*`` keys are their 1-sigma
uncertainties, as a calibration reports them (``deepsync calibrate``).

A cell may give its channel bandwidth (``bandwidth_mhz``, an LTE bandwidth): the cell search
then models its CRS at that bandwidth alone, rather than fitting each of the six, holds the
cell through fades by its whole known frame (codes and CRS), and the timing stage times it by
that frame (``ml_frame``): on the campus bag 0.02 samples RMS from the truth, against 0.08-0.11
by its codes alone. Without one, the sync stage learns it from the cell's stacks once the cell
is confirmed (``deepsync.sync.bandwidths``); until then, the codes alone.

Within a site, either every sector gives its EARFCN or none does (sectors of a site are paired
by carrier: a cell without one would silently drop out of the pair search), a PCI appears at
most once per carrier (two such sectors cannot be told apart), and the position is given
whole (latitude and longitude) or not at all. Across the database a PCI appears on one placed site
per carrier (a cell heard with it could not be placed: a copied site, or a reused PCI whose
carriers are not given), every placed site lies within a cell's reach (``MAX_CELL_RANGE_M``, 100 km) of
the origin (a site 1000 km off, with latitude and longitude swapped, or an origin at the
antipode, would only show later as "too few sites" or "degenerate geometry"), and the epoch
lies in the GPS era (1980..2100).

```yaml
name: campus
origin: {latitude_deg: 38.9869, longitude_deg: -76.9426, height_m: 10.0}   # optional
timing_epoch_utc: "2026-01-01T00:00:00Z"   # optional (required with a drift)
sites:
  - name: A
    latitude_deg: 38.985851      # optional
    longitude_deg: -76.947617    # optional
    height_m: 30.0               # optional, antenna height above ground
    timing_offset_us: 3120.4     # optional, frame timing vs network time (estimate)
    timing_offset_std_us: 0.01   # optional, its 1-sigma
    timing_drift_ns_per_s: -12.0 # optional, how fast the timing moves
    timing_drift_std_ns_per_s: 0.5  # optional, its 1-sigma
    cells:
      - {pci: 120, earfcn: 2000, bandwidth_mhz: 10}   # earfcn, bandwidth_mhz optional
```
"""

from __future__ import annotations

import datetime
import reprlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from deepsync.configio import ConfigError, load_yaml, require_list, require_mapping
from deepsync.geo import geodetic_to_ecef
from deepsync.lte.cell import check_pci
from deepsync.lte.earfcn import downlink_frequency_hz
from deepsync.lte.numerology import check_bandwidth
from deepsync.outputs import replacing
from deepsync.types import MAX_CELL_RANGE_M


EPOCH_RANGE = (datetime.datetime(1980, 1, 6, tzinfo=datetime.timezone.utc),  # the GPS epoch
               datetime.datetime(2100, 1, 1, tzinfo=datetime.timezone.utc))


@dataclass(frozen=True)
class TowerCell:
    pci: int
    earfcn: int | None
    site: str
    bandwidth_mhz: float | None = None  # channel bandwidth, if known

    @property
    def carrier_hz(self) -> float | None:
        return None if self.earfcn is None else downlink_frequency_hz(self.earfcn)


@dataclass(frozen=True)
class TowerSite:
    name: str
    latitude_deg: float | None
    longitude_deg: float | None
    height_m: float | None
    timing_offset_us: float | None
    cells: tuple[TowerCell, ...]
    timing_offset_std_us: float | None = None
    timing_drift_ns_per_s: float | None = None
    timing_drift_std_ns_per_s: float | None = None

    @property
    def has_position(self) -> bool:
        return self.latitude_deg is not None


@dataclass(frozen=True)
class MapOrigin:
    """The ``map`` frame's origin: WGS84 latitude/longitude (deg), ground ellipsoidal height (m)."""

    latitude_deg: float
    longitude_deg: float
    height_m: float


@dataclass(frozen=True)
class TowerDatabase:
    name: str
    sites: tuple[TowerSite, ...]
    origin: MapOrigin | None = None
    timing_epoch_ns: int | None = None  # UTC ns at which the sites' timing offsets hold

    def site(self, name: str) -> TowerSite:
        for site in self.sites:
            if site.name == name:
                return site
        raise KeyError(f"no site named {name!r} in tower database {self.name!r}")

    @property
    def cells(self) -> tuple[TowerCell, ...]:
        return tuple(cell for site in self.sites for cell in site.cells)

    @property
    def pcis(self) -> list[int]:
        return sorted({cell.pci for cell in self.cells})

    def unsized_pcis(self) -> set[int]:
        """PCIs none of whose cells gives a bandwidth (what the sync stage may learn)."""
        return {pci for pci in self.pcis if all(cell.bandwidth_mhz is None for cell in self.cells_with_pci(pci))}

    def cells_with_pci(self, pci: int) -> list[TowerCell]:
        """Every database cell using ``pci`` (PCIs repeat across a network, on other sites)."""
        return [cell for cell in self.cells if cell.pci == pci]

    def bandwidths(self) -> dict[int, float]:
        """PCI -> channel bandwidth (MHz), for the PCIs whose cells give one and agree on it
        (a PCI reused by cells of other bandwidths has none: which one is heard is not known)."""
        given: dict[int, set[float | None]] = {}
        for cell in self.cells:
            given.setdefault(cell.pci, set()).add(cell.bandwidth_mhz)
        return {pci: values.pop() for pci, values in given.items() if len(values) == 1 and None not in values}

    def cosited_pairs(self) -> list[tuple[int, int]]:
        """Pairs of PCIs on one site and one carrier (or carriers not given, which the parser
        allows only for a whole site): sectors whose sync codes arrive at the same time and
        add up before the square law."""
        pairs = set()
        for site in self.sites:
            for i, a in enumerate(site.cells):
                for b in site.cells[i + 1 :]:
                    if a.pci != b.pci and a.earfcn == b.earfcn:
                        pairs.add((min(a.pci, b.pci), max(a.pci, b.pci)))
        return sorted(pairs)


MAX_DRIFT_NS_PER_S = 1000.0  # a +-1000 ppb oscillator, as the twin allows
_TIMING_KEYS = {  # key: (low, high), physical ranges
    "timing_offset_us": (0.0, 10_000.0),  # within one 10 ms frame
    "timing_offset_std_us": (0.0, 10_000.0),
    "timing_drift_ns_per_s": (-MAX_DRIFT_NS_PER_S, MAX_DRIFT_NS_PER_S),
    "timing_drift_std_ns_per_s": (0.0, MAX_DRIFT_NS_PER_S),
}
_SITE_KEYS = {"name", "latitude_deg", "longitude_deg", "height_m", "cells", *_TIMING_KEYS}
_TOP_KEYS = {"name", "origin", "timing_epoch_utc", "sites"}


def _optional_number(site: dict, key: str, where: str, low: float, high: float) -> float | None:
    value = site.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
        raise ConfigError(f"{where}.{key}: expected a number in [{low:g}, {high:g}], got {reprlib.repr(value)}")
    return float(value)


def _check_site_cells(cells: list[TowerCell], at: str) -> None:
    """Sectors of a site are paired by carrier (``cosited_pairs``), so either all give their
    EARFCN or none does; and one PCI twice on one carrier of a site is one cell, listed twice
    or mistyped."""
    missing = [j for j, cell in enumerate(cells) if cell.earfcn is None]
    if 0 < len(missing) < len(cells):
        given = [j for j in range(len(cells)) if j not in missing]
        raise ConfigError(
            f"{at}.cells: earfcn given for {_cell_list(given)} but not for "
            f"{_cell_list(missing)}; give it for every sector of site {cells[0].site!r} or for "
            "none (sectors of a site are paired by carrier)"
        )
    first: dict[tuple[int, int | None], int] = {}
    for j, cell in enumerate(cells):
        key = (cell.pci, cell.earfcn)
        if key in first:
            carrier = "without an EARFCN" if cell.earfcn is None else f"on EARFCN {cell.earfcn}"
            raise ConfigError(
                f"{at}.cells[{j}].pci: PCI {cell.pci} {carrier} is already used by "
                f"{at}.cells[{first[key]}] (two sectors of one site with the same PCI on one "
                "carrier cannot be told apart)"
            )
        first[key] = j


def _cell_list(indices: list[int]) -> str:
    return ", ".join(f"cells[{j}]" for j in indices)


def parse_tower_database(data: object, where: str = "towers") -> TowerDatabase:
    """Tower database from a mapping (see the module docstring); errors name the field."""
    top = require_mapping(data, where)
    unknown = sorted(set(top) - _TOP_KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown key {', '.join(unknown)} (known: {', '.join(sorted(_TOP_KEYS))})")
    sites = []
    names = set()
    for i, raw_site in enumerate(require_list(top.get("sites"), f"{where}.sites")):
        at = f"{where}.sites[{i}]"
        site = dict(require_mapping(raw_site, at))
        unknown = sorted(set(site) - _SITE_KEYS)
        if unknown:
            raise ConfigError(f"{at}: unknown key {', '.join(unknown)} (known: {', '.join(sorted(_SITE_KEYS))})")
        name = site.get("name")
        if not isinstance(name, str) or not name or name in names:
            raise ConfigError(f"{at}.name: a unique, non-empty site name is required, got {reprlib.repr(name)}")
        names.add(name)
        cells = []
        for j, raw_cell in enumerate(require_list(site.get("cells"), f"{at}.cells")):
            cell_at = f"{at}.cells[{j}]"
            cell = require_mapping(raw_cell, cell_at)
            if set(cell) - {"pci", "earfcn", "bandwidth_mhz"} or "pci" not in cell:
                raise ConfigError(f"{cell_at}: expected keys pci and optional earfcn, bandwidth_mhz, got {sorted(cell)}")
            try:
                pci = check_pci(cell["pci"])
                earfcn = cell.get("earfcn")
                if earfcn is not None:
                    downlink_frequency_hz(earfcn)  # validates it
                    earfcn = int(earfcn)
            except ValueError as error:
                raise ConfigError(f"{cell_at}: {error}") from None
            bandwidth = cell.get("bandwidth_mhz")
            if bandwidth is not None:
                if isinstance(bandwidth, bool) or not isinstance(bandwidth, (int, float)):
                    raise ConfigError(f"{cell_at}.bandwidth_mhz: expected a number of MHz, "
                                      f"got {reprlib.repr(bandwidth)}")
                try:
                    bandwidth = check_bandwidth(bandwidth)
                except ValueError as error:
                    raise ConfigError(f"{cell_at}.bandwidth_mhz: {error}") from None
            cells.append(TowerCell(pci, earfcn, name, bandwidth))
        if not cells:
            raise ConfigError(f"{at}.cells: a site needs at least one cell")
        _check_site_cells(cells, at)
        latitude = _optional_number(site, "latitude_deg", at, -90, 90)
        longitude = _optional_number(site, "longitude_deg", at, -180, 180)
        if (latitude is None) != (longitude is None):
            raise ConfigError(f"{at}: give both latitude_deg and longitude_deg, or neither "
                              "(half a position cannot anchor a fix)")
        sites.append(TowerSite(
            name=name,
            latitude_deg=latitude,
            longitude_deg=longitude,
            height_m=_optional_number(site, "height_m", at, 0, 1000),
            cells=tuple(cells),
            **{key: _optional_number(site, key, at, *bounds) for key, bounds in _TIMING_KEYS.items()},
        ))
    if not sites:
        raise ConfigError(f"{where}.sites: the database lists no sites")
    name = top.get("name", "")
    if not isinstance(name, str):
        raise ConfigError(f"{where}.name: expected a string, got {reprlib.repr(name)}")
    _check_reused_pcis(sites, where)
    origin = _origin(top.get("origin"), f"{where}.origin")
    _check_reach(sites, origin, where)
    epoch_ns = _epoch_ns(top.get("timing_epoch_utc"), f"{where}.timing_epoch_utc")
    drifting = [site.name for site in sites if site.timing_drift_ns_per_s]
    if drifting and epoch_ns is None:
        raise ConfigError(f"{where}.timing_epoch_utc: sites {', '.join(drifting)} give a timing drift, which "
                          "needs the instant their offsets hold")
    return TowerDatabase(name, tuple(sites), origin, epoch_ns)


def _check_reused_pcis(sites: list[TowerSite], where: str) -> None:
    """ConfigError when two placed sites carry one PCI on one carrier (or either without a
    carrier): the fusion stage could not tell which site a cell heard with it is. (Sites without
    a position only name cells for the search, where a reused PCI is one more to look for.)"""
    seen: dict[int, list[tuple[int, int, TowerCell]]] = {}
    for i, site in enumerate(sites):
        if not site.has_position:
            continue
        for j, cell in enumerate(site.cells):
            for k, l, other in seen.get(cell.pci, []):
                if k != i and (cell.earfcn is None or other.earfcn is None or cell.earfcn == other.earfcn):
                    carrier = "" if cell.earfcn is None or other.earfcn is None else f" on EARFCN {cell.earfcn}"
                    raise ConfigError(
                        f"{where}.sites[{i}].cells[{j}].pci: PCI {cell.pci}{carrier} is also on site {other.site!r} "
                        f"({where}.sites[{k}].cells[{l}]): a cell heard with it could not be placed (a copied site? "
                        "a reused PCI needs the carriers that tell its sites apart)")
            seen.setdefault(cell.pci, []).append((i, j, cell))


def _check_reach(sites: list[TowerSite], origin: MapOrigin | None, where: str) -> None:
    """ConfigError when a placed site lies beyond a cell's reach of the origin, naming it, with
    latitude and longitude swapped when that would place it, or the origin when every site is
    far from it (a misplaced origin)."""
    placed = [(i, site) for i, site in enumerate(sites) if site.has_position]
    if origin is None or not placed:
        return
    centre = geodetic_to_ecef(origin.latitude_deg, origin.longitude_deg, origin.height_m)

    def distance(latitude: float, longitude: float, site: TowerSite) -> float:
        point = geodetic_to_ecef(latitude, longitude, origin.height_m + (site.height_m or 0.0))
        return float(np.linalg.norm(point - centre))

    away = [(i, site, distance(site.latitude_deg, site.longitude_deg, site)) for i, site in placed]
    far = [(i, site, d) for i, site, d in away if d > MAX_CELL_RANGE_M]
    if not far:
        return
    if len(far) == len(away) > 1:
        nearest = min(d for _, _, d in far)
        raise ConfigError(f"{where}.origin: every site lies {nearest / 1e3:,.0f} km or more from it, beyond the "
                          f"{MAX_CELL_RANGE_M / 1e3:g} km a cell reaches: is the origin ({origin.latitude_deg}, "
                          f"{origin.longitude_deg}) misplaced?")
    i, site, d = far[0]
    hint = ""
    if -90 <= site.longitude_deg <= 90 and distance(site.longitude_deg, site.latitude_deg, site) <= MAX_CELL_RANGE_M:
        hint = " (with latitude and longitude swapped it would lie within reach: swapped?)"
    raise ConfigError(f"{where}.sites[{i}]: site {site.name!r} is {d / 1e3:,.0f} km from the origin, beyond the "
                      f"{MAX_CELL_RANGE_M / 1e3:g} km a cell reaches{hint}")


def _origin(value: object, where: str) -> MapOrigin | None:
    if value is None:
        return None
    origin = dict(require_mapping(value, where))
    if set(origin) != {"latitude_deg", "longitude_deg", "height_m"}:
        raise ConfigError(f"{where}: expected keys latitude_deg, longitude_deg, height_m, got {sorted(origin)}")
    bounds = {"latitude_deg": (-90, 90), "longitude_deg": (-180, 180), "height_m": (-1000, 9000)}
    values = {key: _optional_number(origin, key, where, *bounds[key]) for key in bounds}
    for key, value in values.items():
        if value is None:
            raise ConfigError(f"{where}.{key}: required (a number in [{bounds[key][0]}, {bounds[key][1]}]), got null")
    return MapOrigin(**values)


def _epoch_ns(value: object, where: str) -> int | None:
    """UTC instant as ns since the Unix epoch, from an ISO 8601 string with a zone."""
    if value is None:
        return None
    if isinstance(value, datetime.datetime):  # YAML reads an unquoted timestamp as one
        instant = value
    elif isinstance(value, str):
        try:
            instant = datetime.datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError:
            raise ConfigError(f"{where}: {reprlib.repr(value)} is not an ISO 8601 time "
                              "(e.g. 2026-01-01T00:00:00Z)") from None
    else:
        raise ConfigError(f"{where}: expected an ISO 8601 time string, got {reprlib.repr(value)}")
    if instant.tzinfo is None:
        raise ConfigError(f"{where}: {reprlib.repr(value)} has no time zone (end it with Z for UTC)")
    if not EPOCH_RANGE[0] <= instant <= EPOCH_RANGE[1]:
        raise ConfigError(f"{where}: {reprlib.repr(value)} lies outside "
                          f"{EPOCH_RANGE[0]:%Y-%m-%d}..{EPOCH_RANGE[1]:%Y-%m-%d} "
                          "(LTE site clocks are set from GPS time)")
    delta = instant - datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc)
    return (delta.days * 86_400 + delta.seconds) * 10**9 + delta.microseconds * 1000


def load_tower_database(path: str | Path) -> TowerDatabase:
    return parse_tower_database(load_yaml(path), str(path))


def tower_database_to_dict(db: TowerDatabase) -> dict:
    """The mapping :func:`parse_tower_database` reads back as ``db`` exactly (values left out
    where they are None); the epoch as an ISO 8601 UTC string ending in Z."""
    top: dict = {"name": db.name}
    if db.origin is not None:
        top["origin"] = {"latitude_deg": db.origin.latitude_deg, "longitude_deg": db.origin.longitude_deg,
                         "height_m": db.origin.height_m}
    if db.timing_epoch_ns is not None:
        top["timing_epoch_utc"] = _epoch_utc(db.timing_epoch_ns)
    sites = []
    for site in db.sites:
        entry = {"name": site.name}
        for key in ("latitude_deg", "longitude_deg", "height_m", *_TIMING_KEYS):
            if getattr(site, key) is not None:
                entry[key] = getattr(site, key)
        entry["cells"] = [{key: value for key, value in (("pci", cell.pci), ("earfcn", cell.earfcn),
                                                         ("bandwidth_mhz", cell.bandwidth_mhz)) if value is not None}
                          for cell in site.cells]
        sites.append(entry)
    top["sites"] = sites
    return top


def _epoch_utc(epoch_ns: int) -> str:
    """ISO 8601 UTC text of an instant in ns; the parser reads microseconds, so no finer."""
    seconds, nanoseconds = divmod(epoch_ns, 10**9)
    if nanoseconds % 1000:
        raise ValueError(f"timing_epoch_ns {epoch_ns} has a sub-microsecond part, which ISO 8601 text in the "
                         "database does not keep")
    instant = datetime.datetime(1970, 1, 1, tzinfo=datetime.timezone.utc) + datetime.timedelta(
        seconds=seconds, microseconds=nanoseconds // 1000)
    fraction = f".{instant.microsecond:06d}" if instant.microsecond else ""
    return instant.strftime("%Y-%m-%dT%H:%M:%S") + fraction + "Z"


def write_tower_database(db: TowerDatabase, path: str | Path, like: str | Path | None = None) -> bool:
    """Write ``db`` as YAML, atomically (:func:`deepsync.outputs.replacing`): a reader, or a crash,
    never meets half a database, and an existing file's permissions are kept. ``like``: the
    database file ``db`` was made from (a calibration's input): its comments, order and layout
    are kept and only what changed is written (``ruamel.yaml``'s round trip). Returns whether
    they were: False where the merged text would not read back as ``db`` exactly (then the plain
    dump is written, which always does)."""
    text = yaml.safe_dump(tower_database_to_dict(db), sort_keys=False)
    kept = False
    if like is not None:
        merged = _merged_text(Path(like), tower_database_to_dict(db))
        if tower_database_to_dict(parse_tower_database(yaml.safe_load(merged))) == tower_database_to_dict(db):
            text, kept = merged, True
    with replacing(path) as temporary:
        temporary.write_text(text, encoding="utf-8")
    return kept


def _merged_text(original: Path, values: dict) -> str:
    """``original``'s YAML text with ``values`` written into it where they differ."""
    import io

    from ruamel.yaml import YAML

    yaml_rt = YAML()  # round trip: comments, key order, flow style and quoting as they were
    yaml_rt.preserve_quotes = True
    yaml_rt.width = 4096  # no new line breaks in long flow mappings
    yaml_rt.indent(mapping=2, sequence=4, offset=2)  # the layout of config/towers: "  - name: A"
    document = yaml_rt.load(original.read_text(encoding="utf-8"))
    out = io.StringIO()
    yaml_rt.dump(_merge(document, values), out)
    return out.getvalue()


def _merge(old: object, new: object) -> object:
    """``new`` written into ``old`` (ruamel's commented mappings and sequences) in place, so what
    did not change keeps its comments and layout; keys and items ``new`` lacks are removed."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in [k for k in old if k not in new]:
            del old[key]
        order = list(new)
        for key, value in new.items():
            if key in old:
                old[key] = _merge(old[key], value)
                continue
            # a new key goes where ``new`` has it: before the first old key that follows it there
            later = [k for k in order[order.index(key) + 1:] if k in old]
            position = list(old).index(later[0]) if later else len(old)
            old.insert(position, key, value)
        return old
    if isinstance(old, list) and isinstance(new, list):
        for index, value in enumerate(new):
            if index < len(old):
                old[index] = _merge(old[index], value)
            else:
                old.append(value)
        del old[len(new):]
        return old
    if isinstance(old, bool) != isinstance(new, bool):
        return new
    if old == new:
        return old  # unchanged: its spelling stays (3120.40, an epoch in quotes)
    if isinstance(old, str) and isinstance(new, str) and type(old) is not str:
        return type(old)(new)  # quoted as it was: an epoch unquoted would read as a YAML timestamp
    return new
