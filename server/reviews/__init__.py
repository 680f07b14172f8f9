"""After a run: the acknowledgement a fall or fault needs before the robot runs again, and the therapist's
SOAP notes of the run (issue 16)."""
