from django.contrib import admin
from django.contrib.auth import views as auth_views
from django.urls import include, path

from lifecycle_site.login_form import LoginForm
from lifecycle_site.monitoring import views as monitoring

admin.site.site_header = "ROS 2 lifecycle manager"
admin.site.site_title = "Lifecycle manager admin"

urlpatterns = [
    path("login/", auth_views.LoginView.as_view(authentication_form=LoginForm), name="login"),
    path("logout/", auth_views.LogoutView.as_view(), name="logout"),
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
