"""A node's parameters as one flat mapping, for the pure parameter rules (no rclpy, no bus).

A vendor module's `validate(params) -> list[str]` and the common rules in `params.validate` get
every parameter of the node by its ROS name ('publish_rate_hz', 'drives', 'drives.axis1.unit_id')
and return one line per broken rule, naming the parameter, the value and what is allowed. The same
function checks the params file at start-up and every `ros2 param set` at run time (on the
current values with the change applied), so it builds nothing and changes nothing.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

DRIVES = 'drives'


def drive_names(params: Mapping[str, Any]) -> list[str]:
    return [n for n in params.get(DRIVES) or () if n]


def bus_params(params: Mapping[str, Any]) -> dict[str, Any]:
    """The bus-level parameters (every name that is not drives or drives.<name>.*)."""
    return {k: v for k, v in params.items() if k != DRIVES and not k.startswith(DRIVES + '.')}


def drive_params(params: Mapping[str, Any], name: str) -> dict[str, Any]:
    """drives.<name>.* without the prefix."""
    prefix = f'{DRIVES}.{name}.'
    return {k[len(prefix):]: v for k, v in params.items() if k.startswith(prefix)}


def link_params(params: Mapping[str, Any], name: str,
                drive_bus_params: tuple[str, ...] = ()) -> dict[str, Any]:
    """The bus parameters of drive `name`: the bus-level ones, with the drive's own link
    parameters (Vendor.drive_bus_params; '' and 0 mean "as the bus") where it sets them."""
    link = bus_params(params)
    own = drive_params(params, name)
    for key in drive_bus_params:
        if own.get(key) not in (None, '', 0):
            link[key] = own[key]
    return link


def drive_view(params: Mapping[str, Any], name: str,
               drive_bus_params: tuple[str, ...] = ()) -> dict[str, Any]:
    """What the vendor's make_drive gets for drive `name`: its link parameters and its own."""
    own = {k: v for k, v in drive_params(params, name).items() if k not in drive_bus_params}
    return {**link_params(params, name, drive_bus_params), **own}


def first_error(check: Callable[..., Any], *args: Any) -> list[str]:
    """[] when check(*args) passes, else [its ValueError's one line]: vendor checks raise
    ValueError so that make_bus/make_drive can run them too."""
    try:
        check(*args)
    except ValueError as e:
        return [str(e)]
    return []


def check_each(params: Mapping[str, Any], link_check: Callable[[Mapping[str, Any]], Any] | None,
               drive_check: Callable[[str, Mapping[str, Any]], Any] | None,
               drive_bus_params: tuple[str, ...] = ()) -> list[str]:
    """Run `link_check(link params)` once per distinct link and `drive_check(name, view)` per
    drive (view as drive_view); the errors in drive order, each once."""
    errors: list[str] = []
    for name in drive_names(params):
        if link_check is not None:
            errors += first_error(link_check, link_params(params, name, drive_bus_params))
        if drive_check is not None:
            errors += first_error(drive_check, name, drive_view(params, name, drive_bus_params))
    return list(dict.fromkeys(errors))
