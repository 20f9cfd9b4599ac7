from django.urls import path

from lifecycle_site.alerts import views

app_name = "alerts"
urlpatterns = [
    path("", views.alert_list, name="list"),
    path("count", views.count, name="count"),
    path("<int:alert_id>/acknowledge", views.acknowledge, name="acknowledge"),
]
