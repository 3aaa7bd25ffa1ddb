"""How candidates are ranked on held-out data: one paired comparison of their
held-out squared residuals, used to pick a family's most specific member,
to order the claimable candidates and to find those the data cannot tell
from the best."""

from __future__ import annotations

from ..stats import not_worse, paired_behind  # noqa: F401  (re-exported for select and image_select)


def choose_members(rows: list[dict], cands, evals) -> None:
    """Per family, keep the most specific member that predicts held-out data
    as well as the family's best (paired difference within two standard
    errors, and 3); the others are not claimable (in place, with the reason)."""
    row_of = {r["effect"]: r for r in rows}
    fams = {}
    for c in cands:
        fams.setdefault(c.family_key, []).append(c)
    for fam, members in fams.items():
        if len(members) < 2:
            continue
        fit = [c for c in members if not row_of[c.label].get("degenerate") and not row_of[c.label].get("impossible")]
        if not fit:
            continue
        best = max(fit, key=lambda c: row_of[c.label]["heldout_gain_chi2"])
        pick = best
        for c in sorted(fit, key=lambda c: (c.k, -row_of[c.label]["heldout_gain_chi2"])):
            if c.k >= best.k:
                break
            behind, se = paired_behind(evals[c.label]["heldout_r2"], evals[best.label]["heldout_r2"])
            if not_worse(behind, se):
                pick = c
                break
        for c in members:
            r = row_of[c.label]
            r["family"] = fam
            if c is pick:
                r["family_choice"] = True
                continue
            if r["claimable"]:
                r["claimable"] = False
            r["not_chosen"] = (f"{pick.label} ({pick.k} parameters) predicts held-out data as well"
                               if c.k > pick.k else f"{pick.label} predicts held-out data better")


# Two effects whose held-out gains differ by less than this fraction of the
# best's explain the same signal: what is left between them is the detail of
# each one's form (an independent simulator's latency against ours reads
# 1-2 % apart on a scan with one speed per direction), not the physics.
FORM_MARGIN = 0.025


def rank(rows: list[dict], heldout_r2: dict) -> tuple[list[dict], list[str]]:
    """Sort candidate rows by held-out gain (in place); return the claimable
    ones, best first, and the labels of those the held-out data cannot tell
    from the best: a paired comparison of their held-out squared residuals
    (``heldout_r2``: label -> per-observation array) whose difference is
    within two standard errors (and at least 3), or within ``FORM_MARGIN``
    of the best's gain. Each row gets ``behind_best_chi2`` and its standard
    error."""
    rows.sort(key=lambda r: -r["heldout_gain_chi2"])
    claimed = [r for r in rows if r["claimable"]]
    if not claimed:
        return [], []
    best = claimed[0]
    ambiguous = []
    for r in claimed[1:]:
        behind, se = paired_behind(heldout_r2[r["effect"]], heldout_r2[best["effect"]])
        r["behind_best_chi2"], r["behind_best_stderr"] = behind, se
        if not_worse(behind, se) or behind < FORM_MARGIN * best["heldout_gain_chi2"]:
            ambiguous.append(r["effect"])
    return claimed, ambiguous
