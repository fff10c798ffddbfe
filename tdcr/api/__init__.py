"""The request and answer contract of every entry point: JSON schemas (:mod:`tdcr.api.schemas`), the
value checks (:mod:`tdcr.api.checks`) and the one validation path (:mod:`tdcr.api.validation`)."""
