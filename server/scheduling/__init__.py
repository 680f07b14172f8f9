"""Scheduled sessions: bookings of a patient on a robot with a prescription version; recurring series;
conflict detection (no robot and no patient double-booked); an iCalendar feed per therapist."""
