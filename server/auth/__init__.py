"""Authentication: argon2 passwords, signed bearer tokens / session cookies, login throttling, role checks."""
