"""One verdict from the geometric and the image level."""

from __future__ import annotations

from .image_locate import COMPONENTS, describe as describe_image


def image_located(item: dict) -> dict:
    """A located image item as an entry of the diagnosis' top-level ``located``."""
    key = item["variable"] if item["curve"] == "residual" else item["curve"]
    return dict(item, level="image", component=COMPONENTS[key], description=describe_image(item))


def merge_levels(geometric: dict, image: dict | None) -> dict:
    """The geometric result with the image level's findings joined in.

    Detector lag leaves a ghost of the previous frame that pulls each
    shadow's centroid back along its motion, which the geometric level can
    only read as a negative encoder latency. When the image level sees the
    ghost, the latency claim is credited to lag instead.
    """
    out = dict(geometric)
    for e in out["effects"]:
        e.setdefault("level", "geometry")
    if image is None:
        return out
    out["located"] = list(out.get("located", [])) + [image_located(it) for it in image.get("located", [])]
    effects = list(out["effects"])
    image_effects = list(image["effects"])
    notes = []
    if any(e["effect"] == "detector_lag" for e in image_effects):
        for e in list(effects):
            if e["effect"] == "encoder_latency" and e["parameters"]["latency"] < 0:
                effects.remove(e)
                notes.append("the centroids' lag behind the motion (read as encoder latency "
                             f"{1e3 * e['parameters']['latency']:+.1f} ms) is the detector-lag ghost")
            if e["effect"] == "detector_lag":
                # one effect seen twice: the ghost in the image, its pull on the centres
                effects.remove(e)
                img = next(i for i in image_effects if i["effect"] == "detector_lag")
                img["level"] = "image and geometry"
                img["centroid_pull"] = {"value": e["parameters"]["pull"], "sigma": e["sigma"]["pull"]}
                notes.append(e["statement"])
    out["effects"] = effects + image_effects
    # with nothing named, the geometric level's own sentence (it says what was located)
    geo = ("; ".join(e["statement"] for e in effects) or
           ("no left-out effect beats the noise" if geometric["effects"] else geometric["verdict"]))
    if out.get("ambiguous_with") and effects:
        geo += f" (not distinguishable here from {', '.join(out['ambiguous_with'])})"
    img = image["verdict"]
    out["verdict"] = f"geometry: {geo}. image: {img}" + (f". {'; '.join(notes)}" if notes else "")
    out["notes"] = notes
    return out
