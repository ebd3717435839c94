"""One pair across methods, from what the runs wrote; ``notebooks/explore_pairs.ipynb`` is thin over these."""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from collections.abc import Sequence as SequenceType
from pathlib import Path
from typing import Any

import pandas as pd

from gvbench_nb.evaluation import collapsed_inliers, run_tables
from gvbench_nb.runner import scoring
from gvbench_nb.studies import failures, verifier_inputs

PICKS = ("index", "false_positive", "false_negative")
VIEW_COLUMNS = ["method", "pair_index", "query", "reference", "label", "num_matches", "num_inliers"]
VIEW_COLUMNS += [*collapsed_inliers.INLIER_KEYPOINT_COUNTS, "collapsed", "score"]
VIEW_COLUMNS += ["rank", "n_pairs", "max_false_score", "above_all_false"]


def score_ranks(table: pd.DataFrame) -> pd.Series:
    """Rank of each pair's score among its method's scores: 1 is the highest, and a pair
    tied with others gets the best rank of its tie (1 + the pairs scoring strictly higher)."""
    return table["score"].rank(method="min", ascending=False).astype(int)


def choose_pair(
    tables: dict[str, pd.DataFrame],
    pick: str = "index",
    pair_index: int | None = None,
    pick_method: str | None = None,
    pick_rank: int = 1,
) -> int:
    """The ``pair_index`` to show: itself (``pick='index'``), or ``pick_method``'s ``pick_rank``-th top false
    positive or false negative (default: the first method)."""
    if pick not in PICKS:
        raise ValueError(f"pick must be one of {', '.join(PICKS)}, got {pick!r}")
    first = next(iter(tables.values()))
    if pick == "index":
        if pair_index is None or not 0 <= int(pair_index) < len(first):
            raise ValueError(
                f"pair_index must be a pair of the run, 0 to {len(first) - 1}, got {pair_index!r}; "
                "or set pick to 'false_positive' or 'false_negative'"
            )
        return int(pair_index)
    method = pick_method or next(iter(tables))
    if method not in tables:
        raise ValueError(
            f"pick_method {method!r} is not among the methods shown ({', '.join(tables)}); add it to methods"
        )
    ranked = (failures.top_false_positives if pick == "false_positive" else failures.top_false_negatives)(
        tables[method], int(pick_rank)
    )
    if len(ranked) < int(pick_rank):
        kind = "false" if pick == "false_positive" else "true"
        raise ValueError(f"{method} has {len(ranked)} {kind} pairs, fewer than pick_rank {pick_rank}; lower pick_rank")
    return int(ranked["pair_index"].iloc[int(pick_rank) - 1])


def pair_across_methods(tables: dict[str, pd.DataFrame], pair_index: int) -> pd.DataFrame:
    """One row a method for pair ``pair_index``: counts (with the distinct keypoints among the inliers and
    whether they collapse, ``collapsed_inliers.RULE``), score, its rank among the method's scores, the
    highest false score and whether the pair beats it (counts toward MR)."""
    rows = []
    for method, table in tables.items():
        if not 0 <= pair_index < len(table):
            raise ValueError(
                f"pair_index {pair_index} is outside {method}'s {len(table)} pairs; pick 0 to {len(table) - 1}"
            )
        row = table.iloc[pair_index]
        false_scores = table.loc[table["label"] == 0, "score"]
        max_false = float(false_scores.max()) if len(false_scores) else float("-inf")
        keypoints = [row.get(name, float("nan")) for name in collapsed_inliers.INLIER_KEYPOINT_COUNTS]
        collapsed = bool(collapsed_inliers.collapsed(table.iloc[[pair_index]]).iloc[0])
        matched = [int(row[name]) if pd.notna(row[name]) else None for name in ("num_matches", "num_inliers")]
        counts = (int(row["label"]), *matched, *keypoints, collapsed)  # an imported method matched nothing here
        counts += (row["score"],)
        rank = int(score_ranks(table).iloc[pair_index])
        values = (method, int(row["pair_index"]), row["query"], row["reference"], *counts, rank, len(table))
        rows.append(dict(zip(VIEW_COLUMNS, (*values, max_false, bool(row["score"] > max_false)))))
    view = pd.DataFrame(rows, columns=VIEW_COLUMNS).astype({"num_matches": "Int64", "num_inliers": "Int64"})
    if view[["query", "reference"]].drop_duplicates().shape[0] > 1:
        raise ValueError(
            f"pair {pair_index} is not the same pair in every method's pairs.csv "
            f"({', '.join(view['method'])}); show methods run on the same pairs"
        )
    return view


def shown_table(view: pd.DataFrame) -> Any:
    """The pair's table as the notebook shows it: its rows are methods, so pandas' row numbers are hidden."""
    return view.style.hide(axis="index").format(na_rep="-")  # '-': not measured (an imported method)


def batch_execution() -> bool:
    """Whether this kernel runs a notebook in batch (papermill, nbmake and nbconvert start
    it through nbclient, which passes an in-memory history file), not a live session."""
    if any(arg.startswith("--HistoryManager.hist_file=:memory:") for arg in sys.argv):
        return True
    try:
        from IPython import get_ipython
    except ImportError:
        return True
    shell = get_ipython()
    if shell is None or not hasattr(shell, "kernel"):
        return True  # plain Python or a terminal IPython: nothing to draw widgets in
    # papermill injects its parameters as a cell headed '# Parameters'
    return any(str(source).startswith("# Parameters") for source in shell.user_ns.get("In", []))


def use_widgets(controls: str = "auto") -> bool:
    """``controls``: 'widgets', 'none' or 'auto' (widgets when ipywidgets is installed and
    the kernel is a live session, not a batch run)."""
    if controls not in ("auto", "widgets", "none"):
        raise ValueError(f"controls must be 'auto', 'widgets' or 'none', got {controls!r}")
    if controls == "none":
        return False
    available = importlib.util.find_spec("ipywidgets") is not None
    if controls == "widgets" and not available:
        raise ValueError("controls='widgets' needs ipywidgets (pip install ipywidgets); or set controls='auto'")
    return available and (controls == "widgets" or not batch_execution())


def default_methods(params_file: str | os.PathLike[str], output_dir: str | os.PathLike[str] | None = None) -> list[str]:
    """Every method with results in the params' output folder (``output_dir`` when given),
    in registry order; ``['sift-nn']`` when it holds none, so the error names a command to make it."""
    from gvbench_nb.runner import config

    folder = Path(output_dir) if output_dir else Path(config.load_params(params_file)["output_dir"])
    return scoring.methods_with_results(folder) or ["sift-nn"]


VIEWS = ("table", "matches", "scores")  # what the notebook shows of one pair, top to bottom
FIGURE_FILES = {"table": "explore_pair.csv", "matches": "explore_pair.png", "scores": "explore_scores.png"}


def figure_image(figure: Any, path: Path) -> Any:
    """A figure saved as PNG at ``path`` and closed, returned as an IPython image: displaying
    the image, not the figure, shows every view in a widget's output area as well as in a batch run."""
    import matplotlib.pyplot as plt
    from IPython.display import Image

    from gvbench_nb.evaluation import plots

    plots.save(figure, path)
    plt.close(figure)
    return Image(data=path.read_bytes(), format="png")


def pair_views(
    output_dir: str | os.PathLike[str],
    tables: dict[str, pd.DataFrame],
    pair_index: int,
    figures_dir: str | os.PathLike[str],
    cache_dir: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Every view of one pair (``VIEWS``), each also written to ``figures_dir`` (``FIGURE_FILES``), so the
    folder holds the pair shown."""
    from gvbench_nb.evaluation import plots
    from gvbench_nb.protocol.images import read_image

    figures = Path(figures_dir)
    figures.mkdir(parents=True, exist_ok=True)
    view = pair_across_methods(tables, pair_index)
    view.to_csv(figures / FIGURE_FILES["table"], index=False)
    runs = {m: run_tables.load_run(output_dir, m) for m in view["method"]}
    measured = [m for m, run in runs.items() if "imported" not in run]  # imported scores have no matches to draw
    first = view.iloc[0]
    scores = figure_image(plots.score_histograms(tables, view), figures / FIGURE_FILES["scores"])
    if not measured:
        return {"table": view, "matches": "no matches to draw: only imported scores", "scores": scores}
    run = runs[measured[0]]
    image_root = Path(run["image_root"])
    images = (read_image(image_root / first["query"]), read_image(image_root / first["reference"]))
    query, reference = first["query"], first["reference"]
    lines = {m: verifier_inputs.match_lines(output_dir, m, query, reference, cache_dir) for m in measured}
    kind = "true" if first["label"] == 1 else "false"
    title = f"{run['sequence']} pair {first['pair_index']} ({kind}): {first['query']} | {first['reference']}"
    matches = plots.pair_matches(images, view[view["method"].isin(measured)], lines, title)
    return {"table": view, "matches": figure_image(matches, figures / FIGURE_FILES["matches"]), "scores": scores}


class ExploreControls:
    """The notebook's controls (``pick``, ``pair_index``, ``pick_rank``, ``pick_method``, methods); any change
    redraws every view (``draw(index, methods)``), and a choice that names no pair is said in the status."""

    def __init__(
        self,
        tables: dict[str, pd.DataFrame],
        draw: Callable[[int, list[str]], dict[str, Any]],
        pick: str = "false_positive",
        pair_index: int = 0,
        pick_method: str | None = None,
        pick_rank: int = 1,
        methods: SequenceType[str] | None = None,
    ) -> None:
        import ipywidgets as widgets

        self.tables = tables
        self.draw = draw
        names = list(tables)
        shown = list(methods or names)
        fit = {"style": {"description_width": "initial"}}  # labels whole, not cut to 'pick_met...'
        self.pick = widgets.Dropdown(options=list(PICKS), value=pick, description="pick", **fit)
        # Unbounded: an index out of range is said, not silently clamped to the last pair.
        self.pair_index = widgets.IntText(value=pair_index, description="pair_index", **fit)
        self.pick_rank = widgets.BoundedIntText(value=pick_rank, min=1, max=100_000, description="pick_rank", **fit)
        ranked_by = pick_method if pick_method in shown else shown[0]
        self.pick_method = widgets.Dropdown(options=shown, value=ranked_by, description="pick_method", **fit)
        self.methods = widgets.SelectMultiple(
            options=names, value=tuple(shown), rows=min(8, len(names)), description="methods", **fit
        )
        self.status = widgets.HTML()
        self.areas = {name: widgets.Output() for name in VIEWS}
        self.areas["table"].layout = widgets.Layout(overflow="auto")  # a wide table scrolls inside the cell
        # CSS classes name each control and view on the page (what a browser test finds them by).
        boxes = {"pick": self.pick, "pair-index": self.pair_index, "pick-rank": self.pick_rank}
        boxes |= {"pick-method": self.pick_method, "methods": self.methods, "status": self.status}
        for name, box in [*boxes.items(), *((f"view-{name}", area) for name, area in self.areas.items())]:
            box.add_class(f"gvbench-{name}")
        self.drawn: dict[str, Any] = {}  # the views last drawn, by name
        self._following = False  # set while a box follows another choice, so that it draws once
        for box in (self.pick, self.pick_rank, self.pick_method):
            box.observe(self.redraw, names="value")
        self.methods.observe(self._methods_chosen, names="value")
        self.pair_index.observe(self._index_typed, names="value")

    def widget(self) -> Any:
        import ipywidgets as widgets

        rows = [
            widgets.HBox([self.pick, self.pair_index, self.pick_rank]),
            widgets.HBox([self.pick_method, self.methods]),
        ]
        return widgets.VBox([*rows, self.status, *(self.areas[name] for name in VIEWS)])

    def shown_methods(self) -> list[str]:
        """The methods selected; none selected means all of them (the status says so)."""
        return list(self.methods.value) or list(self.tables)

    def _methods_chosen(self, _change: Any = None) -> None:
        shown = self.shown_methods()
        self._following = True
        try:
            kept = self.pick_method.value if self.pick_method.value in shown else shown[0]
            self.pick_method.options = shown
            self.pick_method.value = kept
        finally:
            self._following = False
        self.redraw()

    def _index_typed(self, _change: Any = None) -> None:
        if self._following:
            return
        if self.pick.value != "index":
            self.pick.value = "index"  # observed: that redraws
        else:
            self.redraw()

    def _say(self, text: str) -> None:
        import html

        self.status.value = html.escape(text)

    def _clear_views(self) -> None:
        self.drawn = {}
        for area in self.areas.values():
            area.clear_output()

    def redraw(self, _change: Any = None) -> None:
        if self._following:
            return
        shown = {method: self.tables[method] for method in self.shown_methods()}
        ranked_by = self.pick_method.value
        try:
            index = choose_pair(shown, self.pick.value, self.pair_index.value, ranked_by, self.pick_rank.value)
        except ValueError as error:
            self._clear_views()  # no figure of an earlier choice stays under the message
            self._say(str(error))
            return
        if self.pair_index.value != index:
            self._following = True
            try:
                self.pair_index.value = index
            finally:
                self._following = False
        self._say(f"drawing pair {index} for {', '.join(shown)}...")
        self.drawn = self.draw(index, list(shown))
        from IPython.display import display

        for name in VIEWS:
            area = self.areas[name]
            area.clear_output(wait=True)
            with area:
                display(shown_table(self.drawn[name]) if name == "table" else self.drawn[name])
        # Last, naming every control: once it reads so, every view shows that choice.
        everything = "" if self.methods.value else " (none selected: all shown)"
        self._say(
            f"pair {index}: pick {self.pick.value}, pick_method {ranked_by}, pick_rank {self.pick_rank.value}; "
            f"methods {', '.join(shown)}{everything}"
        )
