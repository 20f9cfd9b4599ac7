from django.apps import AppConfig


class SignInConfig(AppConfig):
    name = "lifecycle_site.sign_in"
    verbose_name = "Company sign-in"
