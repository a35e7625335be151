"""What the scores of one batch read, and the tables built from it, once per batch."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

from torch import Tensor

from ..stages import enclosed as _enclosed
from ..stages import scoring as _scoring
from ..stages.groups import EdgeGroups

__all__ = ["ScoreMaps"]


@dataclass(eq=False)
class ScoreMaps:
    """What the scores of one batch of equal-sized images read, at the working resolution,
    and the tables built from it (built on first use, then kept for the batch).

    Attributes:
        edges: ``float32 (B, h, w)`` edge magnitudes (Sec. 3.4).
        groups: the batch's :class:`~reeb_torch.stages.groups.EdgeGroups` (Sec. 3.7).
        input_size: ``(H, W)`` of the input images (boxes are returned in those pixels).
        road: ``(B, h, w)`` road mask (eqs. 3–4), or None where no road term reads it.
        grey: ``float32 (B, h, w)`` grey image (the shadow term, the learned ranking's features), or None.
        green: ``int32 (B, h + 1, w + 1)`` green-pixel counts (an integral image already)
            for the vegetation term, or None without it.
    """

    edges: Tensor
    groups: EdgeGroups
    input_size: tuple[int, int]
    road: Tensor | None = None
    grey: Tensor | None = None
    green: Tensor | None = None
    _kept: dict = field(default_factory=dict, repr=False)
    _pending: Callable[[], _enclosed.EnclosedTables] | None = field(default=None, repr=False)

    @property
    def fx(self) -> float:
        """Working pixels per input pixel, horizontally."""
        return self.edges.shape[-1] / self.input_size[1]

    @property
    def fy(self) -> float:
        """Working pixels per input pixel, vertically."""
        return self.edges.shape[-2] / self.input_size[0]

    def _keep(self, key: object, build: Callable[[], object]):
        if key not in self._kept:
            self._kept[key] = build()
        return self._kept[key]

    def tables(self) -> _enclosed.EnclosedTables:
        """The groups' enclosed-sum prefix tables (:func:`~reeb_torch.stages.enclosed.enclosed_tables`);
        where :meth:`start_tables` started them, waits for them."""
        self.settle()
        b, hk, wk = self.edges.shape
        return self._keep("tables", lambda: _enclosed.enclosed_tables(self.groups, b, hk, wk))

    def start_tables(self) -> None:
        """Start :meth:`tables` on the helper thread (CPU only): this thread goes on meanwhile
        and :meth:`tables` collects them. Whoever calls this calls :meth:`settle` before
        the batch ends, whatever happens (the tables are memory the next batch reuses)."""
        if "tables" not in self._kept and self._pending is None and self.edges.device.type == "cpu":
            b, hk, wk = self.edges.shape
            self._pending = _enclosed.enclosed_tables_started(self.groups, b, hk, wk)

    def settle(self) -> None:
        """Wait for the tables :meth:`start_tables` started, if any, and keep them."""
        pending, self._pending = self._pending, None
        if pending is not None:
            self._kept["tables"] = pending()

    def integral(self, name: Literal["edges", "grey", "road"]) -> Tensor:
        """The integral image (:func:`~reeb_torch.stages.scoring.integral_image`) of the
        edge map, the grey image or the road mask."""
        return self._keep(name, lambda: _scoring.integral_image(getattr(self, name), key=f"integral.{name}"))

    def integral_below(self, name: Literal["grey", "road"]) -> Tensor:
        """:meth:`integral` extended past the bottom row (strips below a box read zeros
        there: :func:`~reeb_torch.stages.scoring.extend_below`)."""
        return self._keep((name, "below"), lambda: _scoring.extend_below(self.integral(name)))

    def kept(self, key: str, build: Callable[[], Tensor]) -> Tensor:
        """A table of this batch that a later step builds from these maps (as the learned
        ranking's orientation tables): ``build()`` on first use, then kept for the batch."""
        return self._keep(("kept", key), build)

    def integral_grey_squared(self) -> Tensor:
        """The integral image of the grey image's square (the learned ranking's grey spread)."""
        grey = self.grey
        assert grey is not None, "the grey image (ScoreMaps.grey) was not kept"
        return self._keep("grey2", lambda: _scoring.integral_image(grey * grey))
