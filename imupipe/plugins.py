"""Plugin manager factory, entry-point discovery, the component registry.

One manager per run (``make_registry``), never at import time. Built-ins are
discovered through the same ``imupipe`` entry-point group as third-party plugins.
Each kind's registration hooks run when that kind is first looked up, so a
command imports only the component modules it uses (``imupipe ingest``: the
readers, not the solvers).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import pluggy

from . import hookspecs
from .components import Component
from .errors import PluginError

KINDS = ("readers", "stages", "solvers", "exporters", "executors", "effects")
ENTRY_POINT_GROUP = "imupipe"


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


def _plugin_name_and_dist(pm: pluggy.PluginManager, plugin: object) -> tuple[str, str, str]:
    name = pm.get_name(plugin) or repr(plugin)
    for p, dist in pm.list_plugin_distinfo():
        if p is plugin:
            return name, dist.project_name, dist.version
    return name, "", ""


def make_registry(plugins: Iterable[object] = (), *, entry_points_too: bool = True) -> Registry:
    """A fresh plugin manager with entry-point plugins and any extra ``plugins`` registered.

    Tests pass fixture plugins in ``plugins`` (with ``entry_points_too=False`` to
    isolate them from what is installed).
    """
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    if entry_points_too:
        try:
            pm.load_setuptools_entrypoints(ENTRY_POINT_GROUP)
        except ImportError as exc:
            raise PluginError(f"a plugin in entry-point group {ENTRY_POINT_GROUP!r} failed to import: {exc}") from exc
    for plugin in plugins:
        pm.register(plugin)
    from . import builtin_hooks

    if not pm.is_registered(builtin_hooks):
        pm.register(builtin_hooks, name="imupipe.builtin_hooks")

    registry = Registry(pm)

    def load(kind: str) -> None:
        hook = getattr(pm.hook, f"imupipe_register_{kind}")
        for impl in hook.get_hookimpls():
            plugin_name, dist, dist_version = _plugin_name_and_dist(pm, impl.plugin)

            def register(obj: Any, *, _plugin=plugin_name, _dist=dist, _ver=dist_version) -> None:
                _register(registry, kind, obj, _plugin, _dist, _ver)

            impl.function(register=register)

    registry.components = _ByKind(load)
    return registry


def _register(registry: Registry, kind: str, obj: Any, plugin: str, dist: str, dist_version: str) -> None:
    name = getattr(obj, "name", None) or getattr(obj, "identifier", None)
    if not isinstance(name, str) or not name:
        raise PluginError(f"plugin {plugin!r} registered a {kind[:-1]} without a name: {obj!r}")
    existing = registry.components[kind].get(name)
    if existing is not None:
        raise PluginError(
            f"two plugins register a {kind[:-1]} named {name!r}: {existing.plugin!r} and {plugin!r}; "
            "uninstall one of them or rename its component"
        )
    registry.components[kind][name] = Component(kind, name, obj, plugin, dist, dist_version)
