from django.apps import AppConfig


class SignInConfig(AppConfig):
    name = "lifecycle_site.sign_in"
    verbose_name = "Company sign-in"

    def ready(self) -> None:
        from django.contrib.auth.signals import user_logged_in

        from lifecycle_site.sign_in.accounts import bound_session

        user_logged_in.connect(bound_session, dispatch_uid="sign_in.bound_session")
