from django.contrib import admin
from django.urls import include, path
from django.utils.translation import gettext_lazy
from django.views.i18n import JavaScriptCatalog

from lifecycle_site.languages import views as languages
from lifecycle_site.monitoring import views as monitoring
from lifecycle_site.sign_in import oidc
from lifecycle_site.sign_in import views as sign_in

admin.site.site_header = gettext_lazy("ROS 2 lifecycle manager")
admin.site.site_title = gettext_lazy("Lifecycle manager admin")

urlpatterns = [
    path("login/", sign_in.Login.as_view(), name="login"),
    path("logout/", sign_in.Logout.as_view(), name="logout"),
    # Named as mozilla-django-oidc looks them up; they answer 404 while OIDC is not configured.
    path("oidc/authenticate/", oidc.start, name="oidc_authentication_init"),
    path("oidc/callback/", oidc.callback, name="oidc_authentication_callback"),
    path("language/", languages.choose, name="language"),
    path("jsi18n/", JavaScriptCatalog.as_view(), name="javascript-catalog"),  # the browser scripts' texts
    path("admin/", admin.site.urls),
    path("healthz", monitoring.healthz, name="healthz"),
    path("readyz", monitoring.readyz, name="readyz"),
    path("metrics", monitoring.metrics, name="metrics"),
    path("api/v1/", include("lifecycle_site.api.urls")),
    path("alerts/", include("lifecycle_site.alerts.urls")),
    path("", include("lifecycle_site.dashboard.urls")),
]

# Refused changes (PermissionDenied anywhere, the admin included) are on record.
handler403 = "lifecycle_site.audit.denials.permission_denied"
# A bad request (a Host not allowed, say) answers in the API's JSON shape under /api/.
handler400 = "lifecycle_site.api.auth.bad_request"
