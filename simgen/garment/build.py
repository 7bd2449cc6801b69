"""Build garment templates: generate, skin, check, save (``simgen garment build``).

    from simgen.garment.build import build_garment, build_all
    g = build_garment("tshirt", body)                          # garments/tshirt/ for the open body
    g = build_garment("tshirt", body, target_triangles=1000)   # garments/tshirt_1k/

Naming rule for sizes: the default size (:data:`simgen.garment.templates.DEFAULT_TRIANGLES`) is
saved under the template's own name; any ``target_triangles`` gives a variant named
``NAME_<N/1000>k`` when N is a multiple of 1000 (``tshirt_1k``, ``dress_2k``) and ``NAME_<N>``
otherwise (``tshirt_2500``). :func:`variant_name` applies it.

Where garments go (docs/architecture.md, "Assets"): for the bundled body "open" in
a source checkout, the repository's ``garments/``; otherwise (another body, or simgen installed as a
wheel, whose package folder is never written) ``$SIMGEN_HOME/<body-id>/garments/``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from simgen.errors import InputError
from simgen.garment.templates import (DEFAULT_MATERIALS, DEFAULT_SKINNING, DEFAULT_TRIANGLES, GENERATOR_VERSION,
                                      TEMPLATE_NAMES, generate_template)

__all__ = ["GarmentBuildError", "variant_name", "default_out_dir", "build_garment", "build_all"]


class GarmentBuildError(InputError):
    """A template generated on the given body fails the quality contract (nothing was written)."""


def variant_name(name: str, target_triangles: int | None = None) -> str:
    """Folder / file name of template ``name`` at ``target_triangles`` (None: the default size).

    >>> variant_name("tshirt"), variant_name("tshirt", 1000), variant_name("skirt", 2500)
    ('tshirt', 'tshirt_1k', 'skirt_2500')
    """
    if name not in TEMPLATE_NAMES:
        raise InputError(f"unknown garment template {name!r}; templates are {', '.join(TEMPLATE_NAMES)}")
    if target_triangles is None:
        return name
    n = int(target_triangles)
    return f"{name}_{n // 1000}k" if n % 1000 == 0 else f"{name}_{n}"


def default_out_dir(body) -> Path:
    """Folder that receives garments built for ``body`` (see the module docstring)."""
    import simgen
    from simgen.assets import body_asset_id, bundled_dir, user_dir

    body_id = body_asset_id(body)
    bundled = bundled_dir("garments")
    package = Path(simgen.__file__).resolve().parent
    if body_id == "open" and package not in bundled.resolve().parents:  # a source checkout
        return bundled
    return user_dir("garments", body_id)


def build_garment(name: str, body=None, *, target_triangles: int | None = None, out_dir: str | Path | None = None,
                  skinning: str | None = None, seed: int = 0, strict: bool = True, save: bool = True):
    """Generate template ``name`` on ``body``, compute its skinning weights, check it and save it.

    Args:
        name: one of :data:`TEMPLATE_NAMES`.
        body: a BodyModel (default: the bundled open body).
        target_triangles: size of a coarser (or finer) variant; None is the template's default size.
            The variant's name follows :func:`variant_name`.
        out_dir: folder receiving NAME/ (default :func:`default_out_dir`).
        skinning: "closest" or "diffused" (default: the template's entry in DEFAULT_SKINNING).
        seed: triangulation seed of :func:`generate_template` (0: canonical); also seeds the
            diffused skinning samples.
        strict: raise :class:`GarmentBuildError` (and write nothing) when the quality check fails;
            with False the garment is saved anyway, its report in the metadata.
        save: write the garment folder (False: only return the Garment).

    Returns:
        The :class:`~simgen.garment.garment.Garment`; ``metadata["quality"]`` holds the check report.
    """
    import simgen
    from simgen.assets import body_asset_id
    from simgen.garment.check import check_garment
    from simgen.garment.garment import Garment
    from simgen.garment.skinning import SKINNING_METHODS, compute_skin_weights
    from simgen.garment.waistband import WAISTBANDS, waistband_metadata

    if body is None:
        from simgen.body import load

        body = load("open")
    garment_name = variant_name(name, target_triangles)
    method = DEFAULT_SKINNING[name] if skinning is None else skinning
    if method not in SKINNING_METHODS:
        raise InputError(f"skinning method {method!r} is not one of {', '.join(SKINNING_METHODS)}")

    vertices, faces, info = generate_template(name, body, target_triangles=target_triangles, seed=seed)
    weights = compute_skin_weights(vertices, body, method=method, faces=faces, seed=seed)
    metadata = {
        "template": name,
        "body": {"id": body_asset_id(body), "name": body.name, "hash": body.hash, "model_id": body.model_id},
        "openings": info["openings"],
        "default_material": DEFAULT_MATERIALS[name],
        "made_by": {
            "how": "generated",
            "generator": "simgen.garment.templates.generate_template",
            "generator_version": GENERATOR_VERSION,
            "simgen_version": simgen.__version__,
            "target_triangles": DEFAULT_TRIANGLES[name] if target_triangles is None else int(target_triangles),
            "seed": int(seed),
            "parameters": info["parameters"],
            "landmarks": info["landmarks"],
            "vertices_pushed_out": info["pushed_out"],
            "seconds": info["seconds"],
        },
        "skinning": {"method": method, "seed": int(seed)},
    }
    garment = Garment(garment_name, vertices, faces, weights, metadata)
    if name in WAISTBANDS:
        garment.metadata["waistband"] = waistband_metadata(WAISTBANDS[name])
    report = check_garment(garment, body, template=name)
    garment.metadata["quality"] = report.to_dict()
    if strict and not report.passed:
        failed = "; ".join(f"{item.name}: {item.message}" for item in report.failures)
        raise GarmentBuildError(f"template {name!r} on body {body_asset_id(body)!r} fails the quality check, "
                                f"nothing written ({failed})")
    if save:
        garment.save(default_out_dir(body) if out_dir is None else Path(out_dir))
    return garment


def build_all(body=None, *, names: Sequence[str] = TEMPLATE_NAMES, target_triangles: int | None = None,
              out_dir: str | Path | None = None, strict: bool = True,
              progress: Callable[[str, int, int], None] | None = None) -> list:
    """Build several templates (default: all six) at one size; returns the Garments in order.

    ``progress(name, done, total)`` is called after each garment. The other arguments are those
    of :func:`build_garment`.
    """
    names = list(names)
    for n in names:
        variant_name(n)  # validates every name before any work
    out = []
    for i, n in enumerate(names):
        out.append(build_garment(n, body, target_triangles=target_triangles, out_dir=out_dir, strict=strict))
        if progress is not None:
            progress(n, i + 1, len(names))
    return out
