"""The report: the tables, claims and pages built from the evaluation records (:mod:`orbis2.eval.records`), read
strictly. The figures it draws with (:mod:`orbis2.eval.figures`) sit below it, beside the records, since the
evaluation protocols draw theirs too.
"""
