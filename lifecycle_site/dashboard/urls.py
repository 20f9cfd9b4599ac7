from django.urls import path

from lifecycle_site.dashboard import views

app_name = "dashboard"
urlpatterns = [
    path("", views.fleet, name="fleet"),
]
