"""The automatic survey (paper §3, §5.1): every disc's 3D position and the camera's
intrinsics from a video of the room, by structure from motion over the cards."""

from app.core.survey.reconstruction import SurveyedTarget, SurveyError, SurveyResult, survey

__all__ = ["SurveyError", "SurveyResult", "SurveyedTarget", "survey"]
