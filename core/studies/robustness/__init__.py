"""The ULS-vs-DIM robust-feature selection (Zahs et al.): the maths (`selection`), its report
(`report`, `plots`) and the run from scene bundles (`run`)."""
