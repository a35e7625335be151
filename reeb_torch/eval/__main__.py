"""``python -m reeb_torch.eval --data DIR ...``: the Table 3 benchmark (:mod:`.table3`)."""

from .table3 import main

if __name__ == "__main__":
    main()
