"""zenrl.common"""
