"""The verdict on a method's run: the certificate, the local probe (probe), the optimistic selection (optimistic) and
the status they decide (finalize)."""
