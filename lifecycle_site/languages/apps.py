from django.apps import AppConfig


class LanguagesConfig(AppConfig):
    name = "lifecycle_site.languages"
    verbose_name = "Languages"

    def ready(self) -> None:
        from django.contrib.auth.signals import user_logged_in

        from lifecycle_site.languages import choice

        user_logged_in.connect(choice.remember_at_login, dispatch_uid="languages.remember_at_login")
