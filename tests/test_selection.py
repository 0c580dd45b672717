"""Which row of a group is selected: the best on validation, whatever order rows arrive in,
and marked again when the table grows."""

import math

from vpr_jax.outputs.results import COLUMNS, ResultRow, append_results, read_results


def _row(method="pca", k=0, val=0.5, val_auc=0.5, test=0.5, ds=1, pair="summer-fall"):
    values = dict.fromkeys(COLUMNS, 0)
    values.update(
        season_pair=pair,
        db_season="summer",
        query_season="fall",
        method=method,
        objective="",
        removed_pcs=k,
        ds=ds,
        recall_at_1=test,
        val_recall_at_1=val,
        val_auc_pr=val_auc,
        run=f"{pair}/{method}_k{k:03d}_ds{ds}",
    )
    return ResultRow(**values)


def test_best_validation_row_is_selected_not_the_best_test_row(tmp_path):
    path = tmp_path / "results.csv"
    rows = [
        _row(k=0, val=0.6, test=0.9),
        _row(k=5, val=0.8, test=0.7),
        _row(k=20, val=0.8, val_auc=0.9, test=0.6),  # ties on recall: AUC-PR decides
        _row(k=50, val=0.8, val_auc=0.9, test=0.95),  # full tie: fewer removed PCs
        _row(method="raw", val=0.1),
        _row(k=5, val=0.9, ds=10),
    ]
    for row in reversed(rows):  # arrival order does not matter
        append_results(path, [row])
    chosen = {(r.method, r.ds): r.removed_pcs for r in read_results(path) if r.selected}
    assert chosen == {("pca", 1): 20, ("raw", 1): 0, ("pca", 10): 5}
    # A better count added later takes the mark; exactly one row per group keeps it.
    append_results(path, [_row(k=100, val=0.85)])
    marked = [r for r in read_results(path) if r.selected and (r.method, r.ds) == ("pca", 1)]
    assert [r.removed_pcs for r in marked] == [100]


def test_rows_without_a_validation_score_lose(tmp_path):
    path = tmp_path / "results.csv"
    append_results(path, [_row(k=0, val=math.nan, val_auc=math.nan, test=1.0), _row(k=5, val=0.1)])
    assert [r.removed_pcs for r in read_results(path) if r.selected] == [5]
