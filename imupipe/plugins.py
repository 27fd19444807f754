"""Plugin manager factory, entry-point discovery, the component registry.

One manager per run (``make_registry``), never at import time. Built-ins are
discovered through the same ``imupipe`` entry-point group as third-party plugins.
Each kind's registration hooks run when that kind is first looked up, so a
command imports only the component modules it uses (``imupipe ingest``: the
readers, not the solvers).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import pluggy

from . import hookspecs
from .components import Component
from .errors import PluginError

KINDS = ("readers", "stages", "solvers", "exporters", "executors", "effects")
ENTRY_POINT_GROUP = "imupipe"
log = logging.getLogger("imupipe")


class _ByKind(dict):
    """kind -> {name: Component}; a kind's registration hooks run at its first lookup."""

    def __init__(self, load: Callable[[str], None] | None = None) -> None:
        super().__init__({k: {} for k in KINDS})
        self._load = load
        self._loaded: set[str] = set()

    def __getitem__(self, kind: str) -> dict[str, Component]:
        if kind not in self._loaded and self._load is not None and kind in KINDS:
            self._loaded.add(kind)
            try:
                self._load(kind)
            except BaseException:
                self._loaded.discard(kind)
                super().__getitem__(kind).clear()
                raise
        return super().__getitem__(kind)

    def get(self, kind, default=None):  # dict.get would bypass __getitem__ (no loading)
        return self[kind] if kind in self else default  # noqa: SIM401


@dataclass
class Registry:
    """Everything the plugins registered, by kind and name (each kind loaded on first use)."""

    pm: pluggy.PluginManager
    components: dict[str, dict[str, Component]] = field(default_factory=_ByKind)
    # plugin name -> (distribution, version, why it was left out): raised at import or in a hook,
    # or an entry-point name already taken
    broken: dict[str, tuple[str, str, str]] = field(default_factory=dict)

    def get(self, kind: str, name: str) -> Any:
        """The registered object, or an error naming the known choices."""
        try:
            return self.components[kind][name].obj
        except KeyError:
            known = ", ".join(sorted(self.components[kind])) or "none"
            raise PluginError(f"no {kind[:-1]} named {name!r}; known {kind}: {known}") from None

    def names(self, kind: str) -> list[str]:
        return sorted(self.components[kind])

    def all(self) -> Iterable[Component]:
        for kind in KINDS:
            yield from self.components[kind].values()


class DuplicateComponentError(PluginError):
    """Two plugins register a component of one kind under one name."""


_warned: set[str] = set()  # broken plugins already said in this process


def _plugin_name_and_dist(pm: pluggy.PluginManager, plugin: object,
                          dists: dict[int, tuple[str, str]]) -> tuple[str, str, str]:
    name = pm.get_name(plugin) or repr(plugin)
    if id(plugin) in dists:
        return (name, *dists[id(plugin)])
    for p, dist in pm.list_plugin_distinfo():
        if p is plugin:
            return name, dist.project_name, dist.version
    return name, "", ""


def _load_entry_points(pm: pluggy.PluginManager, broken: dict, dists: dict) -> None:
    """Register every plugin of the entry-point group; one that fails to import is left out.

    imupipe's own entry points come first, and an entry-point name that is
    already taken (a built-in's, or another distribution's) is refused, never
    silently replacing the one registered first.
    """
    from importlib import metadata

    owners: dict[str, str] = {}
    found = []
    for dist in metadata.distributions():
        ours = [ep for ep in dist.entry_points if ep.group == ENTRY_POINT_GROUP]
        if ours:  # only then its metadata: parsing every distribution's costs ~0.04 s
            dist_name = (dist.metadata["name"] or "").strip()
            found += [(dist_name != "imupipe", dist_name, dist.version, ep) for ep in ours]
    found.sort(key=lambda f: f[0])  # stable: the built-ins first
    for _, dist_name, version, ep in found:
        if pm.is_blocked(ep.name):
            continue
        if ep.name in owners or pm.get_plugin(ep.name) is not None:
            owner = owners.get(ep.name, "an already registered plugin")
            if owner == dist_name:
                continue  # the same distribution seen twice on the path
            broken[f"{ep.name} ({dist_name})"] = (
                dist_name, version,
                f"entry-point name {ep.name!r} is already {owner}'s; rename the entry point")
            continue
        owners[ep.name] = dist_name
        try:
            plugin = ep.load()
        except Exception as exc:  # noqa: BLE001 - the plugin's failure, not imupipe's
            broken[ep.name] = (dist_name, version, f"failed to import: {type(exc).__name__}: {exc}")
            continue
        try:
            pm.register(plugin, name=ep.name)
        except ValueError as exc:  # the same module already registered under another name
            broken[ep.name] = (dist_name, version, f"cannot be registered: {exc}")
            continue
        dists[id(plugin)] = (dist_name, version)


def make_registry(plugins: Iterable[object] = (), *, entry_points_too: bool = True) -> Registry:
    """A fresh plugin manager with entry-point plugins and any extra ``plugins`` registered.

    Tests pass fixture plugins in ``plugins`` (with ``entry_points_too=False`` to
    isolate them from what is installed). A plugin that raises at import or in a
    registration hook is left out (``Registry.broken``, listed by ``imupipe
    plugins``, warned once) and the rest works.
    """
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    broken: dict[str, tuple[str, str, str]] = {}
    dists: dict[int, tuple[str, str]] = {}
    if entry_points_too:
        _load_entry_points(pm, broken, dists)
    for plugin in plugins:
        pm.register(plugin)
    from . import builtin_hooks

    if not pm.is_registered(builtin_hooks):
        pm.register(builtin_hooks, name="imupipe.builtin_hooks")

    registry = Registry(pm, broken=broken)

    def load(kind: str) -> None:
        known = set(registry.broken)
        hook = getattr(pm.hook, f"imupipe_register_{kind}")
        for impl in hook.get_hookimpls():
            plugin_name, dist, dist_version = _plugin_name_and_dist(pm, impl.plugin, dists)

            def register(obj: Any, *, _plugin=plugin_name, _dist=dist, _ver=dist_version) -> None:
                _register(registry, kind, obj, _plugin, _dist, _ver)

            try:
                impl.function(register=register)
            except DuplicateComponentError:
                raise
            except Exception as exc:  # noqa: BLE001 - the plugin's failure: leave it out
                _leave_out(registry, impl.plugin, plugin_name, dist, dist_version,
                           f"imupipe_register_{kind} raised {type(exc).__name__}: {exc}")
        _warn_broken(registry, set(registry.broken) - known)

    registry.components = _ByKind(load)
    _warn_broken(registry)
    return registry


def _warn_broken(registry: Registry, names: set[str] | None = None) -> None:
    for name, (dist, _, why) in sorted(registry.broken.items()):
        if names is not None and name not in names:
            continue
        said = f"plugin {name!r} ({dist or 'no distribution'}) is broken and left out: {why}"
        if said not in _warned:
            _warned.add(said)
            log.warning("%s", said)


def _leave_out(registry: Registry, plugin: object, name: str, dist: str, version: str,
               why: str) -> None:
    registry.broken[name] = (dist, version, why)
    for comps in dict.values(registry.components):  # the kinds loaded so far (no new loading)
        for cname in [n for n, c in comps.items() if c.plugin == name]:
            del comps[cname]
    registry.pm.unregister(plugin)


def _register(registry: Registry, kind: str, obj: Any, plugin: str, dist: str, dist_version: str) -> None:
    name = getattr(obj, "name", None) or getattr(obj, "identifier", None)
    if not isinstance(name, str) or not name:
        raise PluginError(f"plugin {plugin!r} registered a {kind[:-1]} without a name: {obj!r}")
    existing = registry.components[kind].get(name)
    if existing is not None:
        raise DuplicateComponentError(
            f"two plugins register a {kind[:-1]} named {name!r}: {existing.plugin!r} and {plugin!r}; "
            "uninstall one of them or rename its component"
        )
    registry.components[kind][name] = Component(kind, name, obj, plugin, dist, dist_version)
