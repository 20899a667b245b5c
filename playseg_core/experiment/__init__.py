"""The paper's augmentation experiment (`playseg experiment`): policies trained on an annotated start split
plus what each condition adds from unannotated play, evaluated in the domain's simulator.

conditions.py says what each condition adds; runner.py builds the data, the segmenters, the added
segments and the policy runs (each cached under the output directory, so a rerun resumes); report.py
writes the table next to the paper's figures and the plots. A domain takes part by exposing
`Domain.experiment` (see `spec.ExperimentSpec`).
"""
