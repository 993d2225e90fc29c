"""The camera URLs of ``rig.frames`` that name an SDK camera (``pylon://``, ``aravis://``): what
each names, read without opening anything, so that a config is checked before any work
(:func:`torchblur.config.checks.validate_rig`) and the camera opens with the same reading
(:mod:`torchblur.hardware.pylon`, :mod:`torchblur.hardware.aravis`).
"""
from __future__ import annotations

from urllib.parse import parse_qs, urlparse

from torchblur.errors import ParameterError

__all__ = ["camera_url_query", "pylon_url_options", "aravis_url_options"]


def camera_url_query(url: str, scheme: str, options: tuple, form: str) -> tuple:
    """A camera URL ``scheme://[NAME][?option=value&...]`` split into ``(netloc, {option: value},
    readout_s)``: the one parser of the SDK cameras' URLs (``pylon://``, ``aravis://``).

    Raises:
        ParameterError: naming ``url``: another scheme (``form`` is the expected one), an option
            not in ``options``, a ``readout_s`` that is not a number (default 0).
    """
    u = urlparse(url)
    if u.scheme != scheme:
        raise ParameterError(f"url: expected {form}, got {url!r}")
    q = {k: v[-1] for k, v in parse_qs(u.query).items()}
    unknown = set(q) - set(options)
    if unknown:
        raise ParameterError(f"url: unknown options {sorted(unknown)}; expected {', '.join(options)}")
    try:
        readout = float(q.get("readout_s", 0.0))
    except ValueError:
        raise ParameterError(f"url: readout_s must be a number of seconds, got {q['readout_s']!r}") from None
    return u.netloc, q, readout


def pylon_url_options(url: str) -> dict:
    """The camera a ``pylon://[SERIAL][?trigger=Line1&pixel_format=Mono12&readout_s=1e-3]`` URL
    names, as :class:`~torchblur.hardware.pylon.PylonCamera`'s arguments (``serial``, ``trigger_source``,
    ``pixel_format``, ``readout_s``); nothing is opened (the config check uses it).

    Raises:
        ParameterError: naming ``url``: another scheme, an unknown option, a readout_s that is
            not a number.
    """
    netloc, q, readout = camera_url_query(url, "pylon", ("trigger", "pixel_format", "readout_s"),
                                          "pylon://[SERIAL][?trigger=...&pixel_format=...]")
    return {"serial": netloc or None, "trigger_source": q.get("trigger", "Line1"), "pixel_format": q.get("pixel_format"),
            "readout_s": readout}


def aravis_url_options(url: str) -> dict:
    """The camera an ``aravis://[DEVICE][?trigger=Line1&pixel_format=Mono16&readout_s=1e-3&feed=tcp://H:P]``
    URL names, as :class:`~torchblur.hardware.aravis.AravisCamera`'s arguments (``device``, ``trigger_source``, ``pixel_format``,
    ``readout_s``, ``feed``: the emulator's camera channel, emulation only); nothing is opened.

    Raises:
        ParameterError: naming ``url``: another scheme, an unknown option, a readout_s that is not a number.
    """
    netloc, q, readout = camera_url_query(url, "aravis", ("trigger", "pixel_format", "readout_s", "feed"),
                                          "aravis://[DEVICE][?trigger=...&pixel_format=...]")
    feed = q.get("feed")
    if feed is not None and not feed.startswith("tcp://"):
        raise ParameterError(f"url: feed must be the emulator's camera channel tcp://HOST:PORT, got {feed!r}")
    return {"device": netloc or None, "trigger_source": q.get("trigger", "Software" if feed else "Line1"),
            "pixel_format": q.get("pixel_format", "Mono16" if feed else None), "readout_s": readout, "feed": feed}
