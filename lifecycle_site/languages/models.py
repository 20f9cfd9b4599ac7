from django.conf import settings
from django.db import models
from django.utils.translation import gettext_lazy


class LanguageChoice(models.Model):
    """The language a user chose in the page header; it follows them to every browser."""

    user = models.OneToOneField(settings.AUTH_USER_MODEL, on_delete=models.CASCADE, related_name="language_choice")
    language = models.CharField(max_length=8, choices=settings.LANGUAGES)

    class Meta:
        verbose_name = gettext_lazy("language choice")
        verbose_name_plural = gettext_lazy("language choices")

    def __str__(self) -> str:
        return f"{self.user}: {self.language}"
