"""Reproductions of the source documents' example figures, one module per document (``reproduce(outdir)``)."""
