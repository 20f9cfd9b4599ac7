"""The password hasher of the test process: Django's PBKDF2 with 1,000 iterations instead of
1,000,000 (0.6 s a hash on a slow core, paid for every test user made and every password login).
Its hashes are ordinary ``pbkdf2_sha256`` ones, so a site process started by a test (production
settings) checks them as it checks any, and raises their iterations at the first login."""
from django.contrib.auth.hashers import PBKDF2PasswordHasher


class QuickPBKDF2PasswordHasher(PBKDF2PasswordHasher):
    iterations = 1_000
