"""The examples installed with kbs (``kbs.examples``): rule files (``rules/``), a predicate plugin
(``plugins/``) and the bundled scenes (``data/``). ``kbs rules list`` lists the rule files as
``examples/NAME`` with the folder they are installed in; ``kbs rules show examples/tabletop >
tabletop.yaml`` copies one, ``kbs run --rules examples/tabletop`` runs it."""
