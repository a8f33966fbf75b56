"""The ULS-vs-DIM robust-feature selection (Zahs et al.): its maths, report, figures and run from scenes."""
