"""Settings of the lifecycle manager.

Everything that differs between a laptop demo and a plant installation comes from the
environment (or an env file the deployment provides). Without any, the product runs on
its embedded defaults: SQLite and a local Redis under ./var, bound to loopback.
"""
from __future__ import annotations

import ipaddress
import os
import secrets
from datetime import timedelta
from pathlib import Path

import dj_database_url
from csp.constants import NONE, SELF
from django.core.exceptions import ImproperlyConfigured

from lifecycle_site.alerts.destinations import Allow, parse_allow
from lifecycle_site.sign_in import config as sign_in_config
from ros_gateway.shared import environment as env
from ros_gateway.shared import protocol

BASE_DIR = Path(__file__).resolve().parent.parent
DATA_DIR = Path(os.environ.get("LIFECYCLE_DATA_DIR", BASE_DIR / "var")).resolve()
DATA_DIR.mkdir(parents=True, exist_ok=True)



def _secret_key() -> str:
    """The key from the environment, else one generated once and kept in the data dir."""
    key = os.environ.get("DJANGO_SECRET_KEY")
    if key:
        return key
    path = DATA_DIR / "secret_key"
    if not path.exists():
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as handle:
            handle.write(secrets.token_urlsafe(50))
    return path.read_text().strip()


SECRET_KEY = _secret_key()
DEBUG = env.flag("DJANGO_DEBUG", False)
ALLOWED_HOSTS = env.items("DJANGO_ALLOWED_HOSTS", "127.0.0.1,localhost,[::1]")
CSRF_TRUSTED_ORIGINS = env.items("DJANGO_CSRF_TRUSTED_ORIGINS", "")
if env.flag("LIFECYCLE_BEHIND_TLS_PROXY", False):
    # The proxy terminates TLS and says so; without this, CSRF origin checks fail behind it.
    SECURE_PROXY_SSL_HEADER = ("HTTP_X_FORWARDED_PROTO", "https")
    SESSION_COOKIE_SECURE = CSRF_COOKIE_SECURE = True
    # Browsers that saw the site over TLS refuse plain HTTP to it for this long. Sent only on
    # answers to HTTPS requests (SecurityMiddleware), so a plain-HTTP demo never gets it.
    SECURE_HSTS_SECONDS = env.whole("LIFECYCLE_HSTS_SECONDS", 365 * 24 * 3600, minimum=0, unit="seconds")
    # Off by default: on a plant network the site's name may be the parent of hosts that serve
    # plain HTTP (the device's own name is usually not).
    SECURE_HSTS_INCLUDE_SUBDOMAINS = env.flag("LIFECYCLE_HSTS_INCLUDE_SUBDOMAINS", False)
# Django's defaults, spelled out because docs/security.md promises them.
SESSION_COOKIE_HTTPONLY = True
SESSION_COOKIE_SAMESITE = CSRF_COOKIE_SAMESITE = "Lax"
SECURE_CONTENT_TYPE_NOSNIFF = True
SECURE_REFERRER_POLICY = "same-origin"
SECURE_CROSS_ORIGIN_OPENER_POLICY = "same-origin"
X_FRAME_OPTIONS = "DENY"
# Content-Security-Policy (django-csp): scripts, styles and sockets from the site itself only;
# no inline script, no eval (htmx is told not to need them: templates/base.html).
CONTENT_SECURITY_POLICY = {
    "DIRECTIVES": {
        "default-src": [SELF],
        "script-src": [SELF],
        "style-src": [SELF],
        "img-src": [SELF],
        "font-src": [SELF],
        "connect-src": [SELF],  # 'self' covers ws:// and wss:// to the same host and port
        "object-src": [NONE],
        "base-uri": [NONE],
        "form-action": [SELF],
        "frame-ancestors": [NONE],
    },
}

# Sub-path behind a reverse proxy that strips it (see lifecycle_site/prefix.py).
URL_PREFIX = os.environ.get("LIFECYCLE_URL_PREFIX", "").rstrip("/")
FORCE_SCRIPT_NAME = URL_PREFIX or None
LIFECYCLE_TRUST_FORWARDED_PREFIX = env.flag("LIFECYCLE_TRUST_FORWARDED_PREFIX", False)

# The site is served by daphne (``python -m lifecycle_site.serve``: make demo, the image). "daphne" is not an app
# here: it only replaces runserver, and importing it (twisted, autobahn, cryptography) costs
# every other process, the gateway and the CLI, ~26 MB.
INSTALLED_APPS = [
    "django.contrib.admin",
    "django.contrib.auth",
    "django.contrib.contenttypes",
    "django.contrib.sessions",
    "django.contrib.messages",
    "django.contrib.staticfiles",
    "channels",
    "django_htmx",
    "axes",
    "lifecycle_site.fleet",
    "lifecycle_site.gateway_link",
    "lifecycle_site.ingest",
    "lifecycle_site.audit",
    "lifecycle_site.api",
    "lifecycle_site.dashboard",
    "lifecycle_site.alerts",
    "lifecycle_site.operations",
    "lifecycle_site.modes",
    "lifecycle_site.diagnostics",
    "lifecycle_site.sign_in",
    "lifecycle_site.languages",
]

MIDDLEWARE = [
    "django.middleware.security.SecurityMiddleware",
    "csp.middleware.CSPMiddleware",
    "whitenoise.middleware.WhiteNoiseMiddleware",
    "lifecycle_site.prefix.ForwardedPrefixMiddleware",
    "lifecycle_site.no_store.NoStoreMiddleware",
    "django.contrib.sessions.middleware.SessionMiddleware",
    "django.middleware.locale.LocaleMiddleware",  # the language cookie, else Accept-Language
    "django.middleware.common.CommonMiddleware",
    "django.middleware.csrf.CsrfViewMiddleware",
    "django.contrib.auth.middleware.AuthenticationMiddleware",
    "lifecycle_site.languages.middleware.UserLanguageMiddleware",  # a signed-in user's own choice wins
    "django.contrib.messages.middleware.MessageMiddleware",
    "django.middleware.clickjacking.XFrameOptionsMiddleware",
    "django_htmx.middleware.HtmxMiddleware",
    "lifecycle_site.database_input.DatabaseInputMiddleware",  # PostgreSQL's DataError: 400, not 500
    "axes.middleware.AxesMiddleware",  # last: answers a locked-out login with the page below
]
# Brute force (django-axes): after LIFECYCLE_LOGIN_FAILURES wrong passwords for one account,
# or from one client address, logins of that account / from that address are refused for
# LIFECYCLE_LOGIN_LOCKOUT_MINUTES (a right password included), on /login/ and /admin/login/.
AUTHENTICATION_BACKENDS = ["axes.backends.AxesStandaloneBackend", "django.contrib.auth.backends.ModelBackend"]
# Company sign-in beside the local accounts (docs/sign-in.md): LDAP / Active Directory through the
# login form, OpenID Connect through its own button. Each is on when its variables are set.
_LDAP = sign_in_config.ldap_settings()
_OIDC = sign_in_config.oidc_settings()
LDAP_ON, OIDC_ON = bool(_LDAP), bool(_OIDC)
LIFECYCLE_DIRECTORY_SESSION_HOURS = sign_in_config.directory_session_hours()
LIFECYCLE_DIRECTORY_TOKEN_DAYS = sign_in_config.directory_token_days()
globals().update(_LDAP)
globals().update(_OIDC)
if LDAP_ON:
    AUTHENTICATION_BACKENDS.append("lifecycle_site.sign_in.ldap.Backend")
if OIDC_ON:
    AUTHENTICATION_BACKENDS.append("lifecycle_site.sign_in.oidc.Backend")
    # Log out (a form) redirects to the provider's logout: as set, else the discovered one on the issuer's origin.
    if OIDC_OP_END_SESSION_URL or OIDC_OP_ISSUER:  # noqa: F821 (set just above)
        CONTENT_SECURITY_POLICY["DIRECTIVES"]["form-action"].append(
            sign_in_config.origin(OIDC_OP_END_SESSION_URL or OIDC_OP_ISSUER))  # noqa: F821
AXES_FAILURE_LIMIT = env.whole("LIFECYCLE_LOGIN_FAILURES", 5, minimum=1, unit="failed logins")
AXES_COOLOFF_TIME = timedelta(minutes=env.number("LIFECYCLE_LOGIN_LOCKOUT_MINUTES", 15, above=0, unit="minutes"))
AXES_LOCKOUT_PARAMETERS = ["username", "ip_address"]
# A good login forgets only that account's failures from that address (login_attempts.py):
# axes' own reset, by account or address, let a good login of one account wipe the failures
# counted against another.
AXES_RESET_ON_SUCCESS = True
AXES_HANDLER = "lifecycle_site.login_attempts.LoginAttempts"
AXES_LOCKOUT_TEMPLATE = "registration/locked_out.html"
AXES_VERBOSE = True
# Refused form posts (a stale page, a forged request) are on record like other refusals.
CSRF_FAILURE_VIEW = "lifecycle_site.audit.denials.csrf_failure"

ROOT_URLCONF = "lifecycle_site.urls"
ASGI_APPLICATION = "lifecycle_site.asgi.application"

TEMPLATES = [
    {
        "BACKEND": "django.template.backends.django.DjangoTemplates",
        "DIRS": [BASE_DIR / "templates"],
        "APP_DIRS": True,
        "OPTIONS": {
            "context_processors": [
                "django.template.context_processors.request",
                "django.contrib.auth.context_processors.auth",
                "django.contrib.messages.context_processors.messages",
            ],
        },
    },
]

# SQLite by default; DATABASE_URL=postgres://USER:PASSWORD@HOST:PORT/NAME for a bigger site
# (psycopg 3; several site instances may share it). Each daphne keeps up to
# http_handler.WORKERS connections, so PostgreSQL's max_connections must cover the instances
# times that, plus the ingest process and the management commands (docker/README.md, PostgreSQL).
DATABASES = {
    "default": dj_database_url.parse(
        os.environ.get("DATABASE_URL", f"sqlite:///{DATA_DIR / 'db.sqlite3'}"), conn_max_age=0
    )
}
if DATABASES["default"]["ENGINE"] == "django.db.backends.postgresql":
    # A database that does not answer fails the request within seconds, not after minutes.
    DATABASES["default"].setdefault("OPTIONS", {}).setdefault("connect_timeout", 10)
    # A process frozen (SIGSTOP, a paused container) inside a transaction holds its row locks:
    # PostgreSQL ends such a session after this long, so the others' writes go on (docs/architecture.md).
    _idle_ms = int(env.number("LIFECYCLE_DB_IDLE_IN_TRANSACTION_S", 10, above=0) * 1000)
    DATABASES["default"]["OPTIONS"].setdefault("options", f"-c idle_in_transaction_session_timeout={_idle_ms}")
elif DATABASES["default"]["ENGINE"] == "django.db.backends.sqlite3":
    # WAL lets the gateway write while the site reads; IMMEDIATE avoids lock upgrades failing.
    DATABASES["default"]["OPTIONS"] = {
        "init_command": "PRAGMA journal_mode=WAL; PRAGMA synchronous=NORMAL;",
        "transaction_mode": "IMMEDIATE",
        "timeout": 20,
    }
DEFAULT_AUTO_FIELD = "django.db.models.BigAutoField"

REDIS_URL = env.text("REDIS_URL", protocol.DEFAULT_REDIS_URL)
# Every consumer waits for its messages in a blocking BZPOPMIN of 5 s (channels-redis's
# RedisChannelLayer.brpop_timeout). The Redis client's read timeout must outlast that pop, or
# a consumer on a quiet page dies with "Timeout reading from" every 5 s and daphne closes its
# socket with 1011: redis-py 8 made that timeout 5 s by default (it had none before, so a
# Redis lost during the pop hung the consumer). Set here whatever the version: 10 s more.
CHANNEL_LAYER_SOCKET_TIMEOUT_S = 15.0


def _channel_layer_retry() -> dict:
    """After a Redis restart the connections the channel layer pooled are dead, and redis-py
    does not try a command again unless told: a WebSocket that drew one failed its handshake
    (HTTP 500) until every dead connection had been drawn once. A dead connection is replaced
    and its command tried again; a timeout is not (a Redis that hangs would only stall longer).
    Pooled connections idle for a while are checked with a PING before use."""
    from redis.asyncio.retry import Retry
    from redis.backoff import ExponentialBackoff
    from redis.exceptions import ConnectionError as RedisConnectionError

    return {
        "retry_on_error": [RedisConnectionError],
        "retry": Retry(ExponentialBackoff(cap=0.5, base=0.05), 2, supported_errors=(RedisConnectionError,)),
        "health_check_interval": 10,
    }


CHANNEL_LAYERS = {
    "default": {
        "BACKEND": "channels_redis.core.RedisChannelLayer",
        "CONFIG": {
            # A dict per host: the keys other than "address" go to redis-py's connection pool.
            "hosts": [{
                "address": REDIS_URL,
                "socket_timeout": CHANNEL_LAYER_SOCKET_TIMEOUT_S,
                "socket_connect_timeout": 5.0,
                **_channel_layer_retry(),
            }],
            "prefix": env.text("LIFECYCLE_CHANNEL_PREFIX", "lifecycle"),
            "capacity": 1000,
            "expiry": 30,
            "group_expiry": 3600,
        },
    }
}

AUTH_PASSWORD_VALIDATORS = [
    {"NAME": "django.contrib.auth.password_validation.UserAttributeSimilarityValidator"},
    {"NAME": "django.contrib.auth.password_validation.MinimumLengthValidator", "OPTIONS": {"min_length": 12}},
    {"NAME": "django.contrib.auth.password_validation.CommonPasswordValidator"},
    {"NAME": "django.contrib.auth.password_validation.NumericPasswordValidator"},
]
LOGIN_URL = "login"
LOGIN_REDIRECT_URL = "dashboard:fleet"
LOGOUT_REDIRECT_URL = "login"

# German and English (docs/translation.md). Pages: the user's choice, else the browser's; e-mails,
# webhooks and the CLI: LIFECYCLE_LANGUAGE (also the pages' fallback).
LANGUAGES = [("en", "English"), ("de", "Deutsch")]
LANGUAGE_CODE = env.text("LIFECYCLE_LANGUAGE", "en").lower()
if LANGUAGE_CODE not in dict(LANGUAGES):
    raise ImproperlyConfigured(f"LIFECYCLE_LANGUAGE={LANGUAGE_CODE!r}: expected one of {', '.join(dict(LANGUAGES))}.")
LOCALE_PATHS = [BASE_DIR / "locale"]
FORMAT_MODULE_PATH = ["lifecycle_site.formats"]  # German numbers keep the decimal point (formats/de)
LANGUAGE_COOKIE_HTTPONLY = True
LANGUAGE_COOKIE_SAMESITE = "Lax"
# The pages, the API, the audit history and the CLI show UTC and say so ("When (UTC)"), whatever
# TZ says (the Edge form's site.timeZone): Django would otherwise render |date in that zone beside
# times its own filters convert to UTC. (Django sets this process's TZ from it, so the site's log
# lines are in UTC too; TZ still sets the zone of the other containers' logs.)
TIME_ZONE = "UTC"
USE_I18N = True
USE_TZ = True

STATIC_URL = STATIC_URL_PATH = "static/"
STORAGES = {
    "default": {"BACKEND": "django.core.files.storage.FileSystemStorage"},
    "staticfiles": {"BACKEND": "lifecycle_site.prefix.PrefixedStaticFilesStorage"},
}
STATICFILES_DIRS = [BASE_DIR / "static"]
STATIC_ROOT = Path(os.environ.get("LIFECYCLE_STATIC_ROOT", DATA_DIR / "staticfiles"))
STATIC_ROOT.mkdir(exist_ok=True)
# Requests reach us with the proxy's prefix already stripped.
WHITENOISE_STATIC_PREFIX = "/static/"
# Serve straight from the source folders unless collectstatic ran (as in the images).
WHITENOISE_USE_FINDERS = not (STATIC_ROOT / "css").exists()
# Request limits (docs/api.md, "Limits"): a body over 1 MiB, files included, is refused with 413
# (by lifecycle_site/serve.py before it is read, and by Django); at most 1000 form or query fields.
DATA_UPLOAD_MAX_MEMORY_SIZE = 1024 * 1024
DATA_UPLOAD_MAX_NUMBER_FIELDS = 1000

LOGGING = {
    "version": 1,
    "disable_existing_loggers": False,
    "formatters": {"plain": {"format": "%(asctime)s %(levelname)s %(name)s: %(message)s"}},
    "handlers": {"console": {"class": "logging.StreamHandler", "formatter": "plain"}},
    "root": {"handlers": ["console"], "level": os.environ.get("LIFECYCLE_LOG_LEVEL", "INFO")},
    # axes: its start banner in every process; failed logins are logged by lifecycle.denials.
    "loggers": {"daphne": {"level": "WARNING"}, "axes": {"level": "WARNING"}},
}

# What the ROS gateway and the site agree on. Times in seconds.
LIFECYCLE = {
    **env.agreed(),  # service timeout, gateway timings, log buffer: ros_gateway/shared/environment.py
    "GATEWAY_OFFLINE_AFTER": env.number("LIFECYCLE_GATEWAY_OFFLINE_AFTER", 10.0, above=0),
    # A group run of a gateway silent this long (and whose facts are all stored) ends failed.
    "RUN_ORPHAN_AFTER": env.number("LIFECYCLE_RUN_ORPHAN_AFTER", 120.0, above=0),
    # Extra wait the site grants the gateway beyond the service timeout before giving up.
    "COMMAND_GRACE": env.number("LIFECYCLE_COMMAND_GRACE", 3.0, above=0),
    # /rosout history kept server-side: per logger (node) count, and age.
    "LOG_KEEP_PER_NODE": env.whole("LIFECYCLE_LOG_KEEP_PER_NODE", 2000, minimum=1, unit="log records"),
    "LOG_KEEP_HOURS": env.number("LIFECYCLE_LOG_KEEP_HOURS", 72.0, above=0, unit="hours"),
    # Bytes each gateway's Redis keys may hold before the site cuts it off (gateway_link/redis_guard.py);
    # None: an eighth of Redis's maxmemory, at most 64 MB (gateway_link.gateway_config.redis_quota).
    "GATEWAY_REDIS_QUOTA": env.megabytes("LIFECYCLE_GATEWAY_REDIS_QUOTA_MB"),
    # A diagnostic status not heard for this long is stale (the gateway says so; diagnostic_aggregator's 5 s).
    "DIAGNOSTICS_STALE_S": env.number("LIFECYCLE_DIAGNOSTICS_STALE_S", protocol.DEFAULT_DIAGNOSTICS_STALE_S,
                                      above=0.5, maximum=3600),
}

# GET /metrics answers without an API token to these client addresses (comma-separated
# addresses or networks, e.g. "127.0.0.1,10.20.0.0/16"); everyone else needs a token.
# Behind a reverse proxy every client has the proxy's address: use a token there.
def _networks(variable: str) -> list[ipaddress.IPv4Network | ipaddress.IPv6Network]:
    networks = []
    for part in filter(None, (p.strip() for p in os.environ.get(variable, "").split(","))):
        try:
            networks.append(ipaddress.ip_network(part, strict=False))
        except ValueError:
            raise ImproperlyConfigured(f"{variable}: {part!r} is not an address or network (e.g. 10.0.0.0/8)") from None
    return networks


LIFECYCLE_METRICS_ALLOW = _networks("LIFECYCLE_METRICS_ALLOW")


# Alert webhooks may reach internal addresses only as listed here: comma-separated addresses,
# networks and host names, e.g. "10.20.0.0/16,tickets.plant" (docs/alerts.md, "Where webhooks may go").
def _webhook_allow(variable: str = "LIFECYCLE_WEBHOOK_ALLOW") -> Allow:
    try:
        return parse_allow(os.environ.get(variable, ""))
    except ValueError as exc:
        raise ImproperlyConfigured(f"{variable}: {exc}") from None


LIFECYCLE_WEBHOOK_ALLOW = _webhook_allow()

# Alerts (docs/alerts.md): evaluated by the ingest process, sent by its delivery threads.
ALERTS = {
    # Link to the site in notifications (e.g. https://edge.plant/lifecycle); empty: no link.
    "SITE_URL": os.environ.get("LIFECYCLE_SITE_URL", "").rstrip("/"),
    # Deliveries waiting; more are dropped.
    "QUEUE_SIZE": env.whole("LIFECYCLE_ALERT_QUEUE", 200, minimum=1, unit="deliveries"),
    "WORKERS": env.whole("LIFECYCLE_ALERT_WORKERS", 2, minimum=1, maximum=64, unit="workers"),
    "TIMEOUT_S": env.number("LIFECYCLE_ALERT_TIMEOUT", 5.0, above=0),  # per webhook request or SMTP session
    "ATTEMPTS": env.whole("LIFECYCLE_ALERT_ATTEMPTS", 5, minimum=1, unit="attempts"),
    "RETRY_BASE_S": env.number("LIFECYCLE_ALERT_RETRY_BASE", 2.0, above=0),  # then 2x, 4x ... up to the cap
    "RETRY_CAP_S": env.number("LIFECYCLE_ALERT_RETRY_CAP", 60.0, above=0),
    "DELIVERY_LOG_KEEP": env.whole("LIFECYCLE_ALERT_DELIVERY_LOG", 2000, minimum=1, unit="deliveries"),
    "RESOLVED_KEEP_DAYS": env.number("LIFECYCLE_ALERT_KEEP_DAYS", 90.0, above=0, unit="days"),
}
# E-mail for alerts (Django's mail): an SMTP server of the plant; nothing is sent without receivers.
EMAIL_BACKEND = os.environ.get("LIFECYCLE_EMAIL_BACKEND", "django.core.mail.backends.smtp.EmailBackend")
EMAIL_HOST = os.environ.get("LIFECYCLE_EMAIL_HOST", "localhost")
EMAIL_PORT = env.whole("LIFECYCLE_EMAIL_PORT", 25, minimum=1, maximum=65535, unit="port")
EMAIL_HOST_USER = os.environ.get("LIFECYCLE_EMAIL_USER", "")
EMAIL_HOST_PASSWORD = os.environ.get("LIFECYCLE_EMAIL_PASSWORD", "")
EMAIL_USE_TLS = env.flag("LIFECYCLE_EMAIL_STARTTLS", False)
EMAIL_USE_SSL = env.flag("LIFECYCLE_EMAIL_TLS", False)
EMAIL_TIMEOUT = ALERTS["TIMEOUT_S"]
DEFAULT_FROM_EMAIL = os.environ.get("LIFECYCLE_EMAIL_FROM", "lifecycle-manager@localhost")
